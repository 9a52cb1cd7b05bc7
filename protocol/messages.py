"""The message schema: one typed dataclass per message, versioned.

Every message has a one-byte type code (``TYPE``) carried in the frame header
and a wire form that is a msgpack map ``{field: value}``. Each field is
declared once, with a *checker* in its metadata; the same checker validates
and normalises the value when a message is encoded and when it is decoded, so
sender and receiver agree on exactly one definition. Arrays travel as real
``np.ndarray`` fields (see :mod:`protocol.codec`); decoded arrays are
read-only views on the received bytes.

Link-level sequence numbers, acknowledgements and sessions live in the frame
header (:mod:`protocol.framing`, :mod:`protocol.arq`), not here; ``Frame.seq``
is the ground simulator's own frame counter that ``Result.frame_seqs`` refers
back to. Type codes 8 and 9 (the version-1 link Ack/Nack messages) are retired.

Fields marked *compressed* travel as zlib'd arrays (codec ext 3); the full
schema with types and limits is in docs/protocol.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields, replace
from typing import Any, ClassVar, TypeVar

import numpy as np

from protocol.errors import InputError

PROTOCOL_VERSION = 2
MAX_TEXT = 4096  # longest free-text field (error text, names)
MAX_SITES = 256
MAX_DICT_ITEMS = 128  # stages, link statistics, camera
MAX_SKIPPED = 32  # pipeline stages a Result can name as skipped
# a Telemetry's notes: few and short, since they share a slow line with the next Result (4 x 256 ASCII chars ~ 8.5 s
# at 1200 baud, within the ground's Telemetry grace: ground_sim.stream.TELEMETRY_LINE_BYTES; characters, not bytes,
# are counted: another script's notes can take up to 4x the bytes)
MAX_NOTES = 4
MAX_NOTE_CHARS = 256
# a Result's no_site_reason that begins so: the flight side withheld the sites of a map its own checks doubt (sensors
# that disagree, a pose the images contradict), not "nothing known safe"; the ground names such maps first
SITES_WITHHELD = "no site is offered on this map"


class SchemaError(InputError):
    """A message field has the wrong type, shape, range or is missing."""


@dataclass(frozen=True)
class Compressed:
    """An array the codec sends zlib-compressed (ext 3) after differencing its last ``delta`` axes (0, 1 or 2).

    The ext 3 filter byte is the number of axes differenced (docs/protocol.md, section 4).
    """

    array: np.ndarray
    delta: int = 0


Checker = Callable[[Any, str], Any]


def _int(lo: int = 0, hi: int = 2**63 - 1) -> Checker:
    def check(v: Any, name: str) -> int:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise SchemaError(f"{name}: expected an integer, got {type(v).__name__}")
        if not lo <= int(v) <= hi:
            raise SchemaError(f"{name}: {int(v)} outside [{lo}, {hi}]")
        return int(v)

    return check


DURATION_SLACK_S = 1e-6  # two clock reads subtracted can land a rounding below 0: no report is lost for it


def _float(finite: bool = True, lo: float | None = None, slack: float = 0.0) -> Checker:
    """A number; with ``lo``, one in ``[lo - slack, lo)`` is taken as ``lo`` and one below that is refused."""

    def check(v: Any, name: str) -> float:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise SchemaError(f"{name}: expected a number, got {type(v).__name__}")
        f = float(v)
        if finite and not math.isfinite(f):
            raise SchemaError(f"{name}: must be finite, got {f}")
        if math.isinf(f):  # "NaN allowed" allows NaN, not an infinity (section 5.4; inf reached results.jsonl)
            raise SchemaError(f"{name}: must be finite or NaN, got {f}")
        if lo is not None and f < lo:  # a duration below 0 was shown as it came ("flight -5.00 s")
            if f < lo - slack:
                raise SchemaError(f"{name}: must be >= {lo:g}, got {f:g}")
            return lo
        return f

    return check


_duration = _float(lo=0.0, slack=DURATION_SLACK_S)


def _bool(v: Any, name: str) -> bool:
    if not isinstance(v, (bool, np.bool_)):
        raise SchemaError(f"{name}: expected a bool, got {type(v).__name__}")
    return bool(v)


def _str(maxlen: int = MAX_TEXT) -> Checker:
    def check(v: Any, name: str) -> str:
        if not isinstance(v, str):
            raise SchemaError(f"{name}: expected a string, got {type(v).__name__}")
        if len(v) > maxlen:
            raise SchemaError(f"{name}: string of {len(v)} chars exceeds {maxlen}")
        return v

    return check


def _names(max_items: int, maxlen: int = 64) -> Checker:
    item = _str(maxlen)

    def check(v: Any, name: str) -> tuple[str, ...]:
        if not isinstance(v, (list, tuple)) or len(v) > max_items:
            raise SchemaError(f"{name}: expected a list of at most {max_items} names")
        return tuple(item(x, f"{name}[{i}]") for i, x in enumerate(v))

    return check


def _floats(n: int, finite: bool = True) -> Checker:
    item = _float(finite)

    def check(v: Any, name: str) -> tuple[float, ...]:
        if isinstance(v, np.ndarray):
            v = v.tolist()
        if not isinstance(v, (list, tuple)) or len(v) != n:
            raise SchemaError(f"{name}: expected {n} numbers")
        return tuple(item(x, f"{name}[{i}]") for i, x in enumerate(v))

    return check


def _ints(n: int) -> Checker:
    item = _int()

    def check(v: Any, name: str) -> tuple[int, ...]:
        if not isinstance(v, (list, tuple)) or len(v) != n:
            raise SchemaError(f"{name}: expected {n} integers")
        return tuple(item(x, f"{name}[{i}]") for i, x in enumerate(v))

    return check


def _array(dtype: str, ndim: int, shape: tuple[int, ...] | None = None, max_side: int = 8192) -> Checker:
    dt = np.dtype(dtype)

    def check(v: Any, name: str) -> np.ndarray:
        if not isinstance(v, np.ndarray):
            raise SchemaError(f"{name}: expected a numpy array, got {type(v).__name__}")
        if v.dtype != dt:
            if v.dtype.kind not in "biuf" or (dt.kind in "iu" and v.dtype.kind == "f"):
                raise SchemaError(f"{name}: expected dtype {dt}, got {v.dtype}")
            if dt.kind in "iu" and not np.can_cast(v.dtype, dt) and v.size:
                # astype wraps: a state grid of int16 256 read as 0, "safe", and an elevation of 40000 cm as
                # -255 m (QA 64a, H1); a value of another integer type is taken only when it fits
                lo, hi, info = int(v.min()), int(v.max()), np.iinfo(dt)
                if lo < info.min or hi > info.max:
                    raise SchemaError(
                        f"{name}: expected dtype {dt}, got {v.dtype} with values {lo}..{hi} outside its range"
                    )
            v = v.astype(dt)
        if v.ndim != ndim:
            raise SchemaError(f"{name}: expected {ndim}-D, got shape {v.shape}")
        if shape is not None and v.shape != shape:
            raise SchemaError(f"{name}: expected shape {shape}, got {v.shape}")
        if any(s > max_side for s in v.shape):
            raise SchemaError(f"{name}: side {max(v.shape)} exceeds {max_side}")
        return v

    return check


def _optional(inner: Checker) -> Checker:
    def check(v: Any, name: str) -> Any:
        return None if v is None else inner(v, name)

    return check


def _degrees(lo: float, hi: float) -> Checker:
    def check(v: Any, name: str) -> float:
        f = _float()(v, name)
        if not lo <= f <= hi:
            raise SchemaError(f"{name}: {f} deg outside [{lo:g}, {hi:g}]")
        return f

    return check


def _number_dict(v: Any, name: str) -> dict[str, float | int]:
    if not isinstance(v, dict) or len(v) > MAX_DICT_ITEMS:
        raise SchemaError(f"{name}: expected a dict of at most {MAX_DICT_ITEMS} numbers")
    out: dict[str, float | int] = {}
    for k, x in v.items():
        _str(64)(k, f"{name} key")
        if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
            raise SchemaError(f"{name}[{k!r}]: expected a number, got {type(x).__name__}")
        out[k] = int(x) if isinstance(x, (int, np.integer)) else float(x)
    return out


def _camera(v: Any, name: str) -> dict[str, float | int]:
    d = _number_dict(v, name)
    need = ("width", "height", "fx", "fy", "cx", "cy")
    missing = [k for k in need if k not in d]
    if missing or len(d) != len(need):
        raise SchemaError(f"{name}: need exactly {', '.join(need)} (missing {missing})")
    return {
        "width": _int(1, 65535)(d["width"], f"{name}.width"),
        "height": _int(1, 65535)(d["height"], f"{name}.height"),
        **{k: _float()(d[k], f"{name}.{k}") for k in ("fx", "fy", "cx", "cy")},
    }


def _stages(v: Any, name: str) -> dict[str, dict[str, float]]:
    if not isinstance(v, dict) or len(v) > MAX_DICT_ITEMS:
        raise SchemaError(f"{name}: expected a dict of at most {MAX_DICT_ITEMS} stages")
    out = {}
    for k, t in v.items():
        _str(64)(k, f"{name} key")
        if not isinstance(t, dict) or set(t) != {"wall_s", "cpu_s"}:
            raise SchemaError(f"{name}[{k!r}]: expected {{'wall_s', 'cpu_s'}}")
        out[k] = {
            "wall_s": _duration(t["wall_s"], f"{name}[{k!r}].wall_s"),
            "cpu_s": _duration(t["cpu_s"], f"{name}[{k!r}].cpu_s"),
        }
    return out


def _wire(
    check: Checker,
    default: Any = ...,
    factory: Callable[[], Any] | None = None,
    *,
    compress: bool = False,
    delta: int = 0,
) -> Any:
    meta = {"check": check, "compress": compress, "delta": delta}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    if default is ...:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


def _default_of(f: Any) -> Any:
    return f.default_factory() if f.default_factory is not MISSING else f.default


def _at_default(f: Any, v: Any) -> bool:
    """``v`` (a checked value of field ``f``) is the field's default: None or an empty container."""
    default = _default_of(f)
    if default is None or v is None:
        return v is None and default is None
    return not isinstance(v, np.ndarray) and type(v) is type(default) and v == default


class Message:
    """Base of all messages: ``TYPE`` code plus generic validate / wire conversion."""

    TYPE: ClassVar[int] = 0
    # fields the encoder leaves off the wire while they hold their default (the decoder restores it), so that a
    # peer whose schema predates them still decodes the message (Result: RESULT_FIELD_REV)
    OMIT_AT_DEFAULT: ClassVar[frozenset[str]] = frozenset()

    def validated(self) -> Message:
        """Return a copy whose fields passed their checkers (raises :class:`SchemaError`)."""
        msg = type(self)(
            **{
                f.name: f.metadata["check"](getattr(self, f.name), f"{type(self).__name__}.{f.name}")
                for f in fields(self)  # type: ignore[arg-type]
            }
        )
        msg.check_consistency()
        return msg

    def check_consistency(self) -> None:
        """Cross-field rules (shapes that must agree); fields are already checked one by one."""

    def to_wire(self) -> dict[str, Any]:
        out = {}
        checked = {}
        for f in fields(self):  # type: ignore[arg-type]
            v = f.metadata["check"](getattr(self, f.name), f"{type(self).__name__}.{f.name}")
            checked[f.name] = v
            if f.name in self.OMIT_AT_DEFAULT and _at_default(f, v):
                continue
            if f.name == "sites":
                v = [s.to_wire() for s in v]
            elif f.metadata.get("compress") and isinstance(v, np.ndarray):
                v = Compressed(v, int(f.metadata.get("delta", 0)))
            out[f.name] = v
        type(self)(**checked).check_consistency()
        return out

    @classmethod
    def from_wire(cls, d: Any) -> Message:
        if not isinstance(d, dict):
            raise SchemaError(f"{cls.__name__}: body must be a map, got {type(d).__name__}")
        kwargs = {}
        for f in fields(cls):  # type: ignore[arg-type]
            if f.name in d:
                v = d[f.name]
                if f.name == "sites":
                    if not isinstance(v, list) or len(v) > MAX_SITES:
                        raise SchemaError(f"{cls.__name__}.sites: expected a list of at most {MAX_SITES}")
                    v = [Site.from_wire(s) for s in v]
                kwargs[f.name] = f.metadata["check"](v, f"{cls.__name__}.{f.name}")
            elif f.default is MISSING and f.default_factory is MISSING:
                raise SchemaError(f"{cls.__name__}: missing field {f.name!r}")
        unknown = set(d) - {f.name for f in fields(cls)}  # type: ignore[arg-type]
        if unknown:
            raise SchemaError(f"{cls.__name__}: unknown fields {sorted(map(str, unknown))}")
        msg = cls(**kwargs)
        msg.check_consistency()
        return msg


@dataclass(frozen=True)
class Site:
    """A candidate landing site (world metres; hazard in [0, 1]; margin = 1 - max hazard over the footprint).

    ``z`` may be NaN: a degraded (image-only) result knows where a site is but not its elevation.
    ``p_safe`` (probability the whole footprint is safe) and ``clearance_m`` (distance from the
    centre to the nearest cell not known safe) are NaN when the flight software did not estimate them.
    On the wire a site is a list of 8 numbers in this order.
    """

    x: float
    y: float
    z: float
    hazard: float
    margin: float
    distance_m: float
    p_safe: float = math.nan
    clearance_m: float = math.nan

    _NAMES: ClassVar[tuple[str, ...]] = ("x", "y", "z", "hazard", "margin", "distance_m", "p_safe", "clearance_m")

    _FINITE: ClassVar[tuple[bool, ...]] = (True, True, False, True, True, True, False, False)
    # (low, high) of each bounded field (NaN passes where allowed): a P(safe) of 5.0 or a clearance of -3 m passed
    _RANGE: ClassVar[dict[str, tuple[float, float]]] = {
        "hazard": (0.0, 1.0),
        "margin": (0.0, 1.0),
        "distance_m": (0.0, math.inf),
        "p_safe": (0.0, 1.0),
        "clearance_m": (0.0, math.inf),
    }

    @classmethod
    def _check(cls, v: Any) -> list[float]:
        if not isinstance(v, (list, tuple)) or len(v) != len(cls._NAMES):
            got = "a map" if isinstance(v, dict) else type(v).__name__
            raise SchemaError(f"Site: expected an array of {len(cls._NAMES)} numbers, got {got}")
        out = [_float(fin)(x, f"Site.{n}") for x, n, fin in zip(v, cls._NAMES, cls._FINITE)]
        for f, n in zip(out, cls._NAMES):
            lo, hi = cls._RANGE.get(n, (-math.inf, math.inf))
            if not (math.isnan(f) or lo <= f <= hi):
                bound = f"in [{lo:g}, {hi:g}]" if math.isfinite(hi) else f">= {lo:g}"
                raise SchemaError(f"Site.{n}: must be {bound}, got {f:g}")
        return out

    def to_wire(self) -> list[float]:
        return self._check([getattr(self, n) for n in self._NAMES])

    @classmethod
    def from_wire(cls, v: Any) -> Site:
        if isinstance(v, Site):
            return v
        if isinstance(v, dict):
            missing = [n for n in cls._NAMES[:6] if n not in v]
            if missing:  # "Site.x: expected a number, got NoneType" named no cause
                raise SchemaError(
                    f"Site: expected an array of {len(cls._NAMES)} numbers, or a map with {', '.join(cls._NAMES)};"
                    f" this map lacks {', '.join(missing)}"
                )
            v = [v.get(n, math.nan) for n in cls._NAMES]
        return cls(*cls._check(v))


def _sites(v: Any, name: str) -> list[Site]:
    if not isinstance(v, (list, tuple)) or len(v) > MAX_SITES:
        raise SchemaError(f"{name}: expected a list of at most {MAX_SITES} sites")
    return [Site.from_wire(s) for s in v]


@dataclass(frozen=True)
class Hello(Message):
    """First message each side sends: who it is and which protocol it speaks."""

    TYPE: ClassVar[int] = 1
    role: str = _wire(_str(64))
    protocol_version: int = _wire(_int(0, 255), PROTOCOL_VERSION)
    software: str = _wire(_str(128), "hazard-hil")
    session: int = _wire(_int(0, 2**32 - 1), 0)  # the sender's link session id (0: not given)
    # the optional fields a decoded Hello left out (they read as their defaults): a board that names nobody must
    # not be reported as "hazard-hil" speaking this ground's version
    omitted: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_wire(cls, d: Any) -> Message:
        msg = super().from_wire(d)
        left_out = tuple(f.name for f in fields(cls) if f.name not in d and f.name != "session")  # type: ignore[arg-type]
        if left_out:
            object.__setattr__(msg, "omitted", left_out)
        return msg


@dataclass(frozen=True)
class Config(Message):
    """Run configuration sent ground -> flight: camera (``pairdir.Camera.to_dict()``), budget, deadline."""

    TYPE: ClassVar[int] = 2
    camera: dict = _wire(_camera)
    budget: str = _wire(_str(64))
    deadline_s: float = _wire(_float())
    preset: str = _wire(_str(64), "")
    protocol_version: int = _wire(_int(0, 255), PROTOCOL_VERSION)
    options: dict = _wire(_number_dict, factory=dict)


@dataclass(frozen=True)
class Frame(Message):
    """One descent image with its reported pose and altimeter reading."""

    TYPE: ClassVar[int] = 3
    seq: int = _wire(_int(0, 2**32 - 1))
    capture_time_s: float = _wire(_float())
    position_m: tuple = _wire(_floats(3))
    R_world_to_cam: np.ndarray = _wire(_array("<f8", 2, (3, 3)))
    altimeter_m: float = _wire(_float(finite=False))  # NaN = no altimeter reading
    image: np.ndarray = _wire(_array("|u1", 2))
    pair_id: str | None = _wire(_optional(_str(128)), None)
    frame_index: int | None = _wire(_optional(_int(0, 2**32 - 1)), None)
    # the sun as DESIGN.md defines it (azimuth clockwise from +Y, elevation above the horizontal), if known:
    # a lander has it from the ephemeris and its attitude; the shading cue reads it
    sun_azimuth_deg: float | None = _wire(_optional(_degrees(-360.0, 360.0)), None)
    sun_elevation_deg: float | None = _wire(_optional(_degrees(-90.0, 90.0)), None)


def _positive(v: Any, name: str) -> float:
    f = _float()(v, name)
    if f <= 0:
        raise SchemaError(f"{name}: must be > 0, got {f}")
    return f


CELL_M_RANGE = (1e-3, 1e4)  # a grid cell from 1 mm to 10 km: 1e-300 passed, and every score came back empty


def _cell_size(v: Any, name: str) -> float:
    f = _positive(v, name)
    lo, hi = CELL_M_RANGE
    if not lo <= f <= hi:
        raise SchemaError(f"{name}: must be in [{lo:g}, {hi:g}] m, got {f:g}")
    return f


_STATE_CODES = np.array([0, 1, 2, 255], np.uint8)  # protocol.pairdir.STATE_SAFE/UNSAFE/UNKNOWN/OUTSIDE


def _states(inner: Checker) -> Checker:
    def check(v: Any, name: str) -> np.ndarray:
        arr = inner(v, name)
        if arr.size and not np.isin(arr, _STATE_CODES).all():
            raise SchemaError(f"{name}: state codes must be 0 safe, 1 unsafe, 2 unknown or 255 outside")
        return arr

    return check


def _values_or_nan(inner: Checker, lo: float, hi: float, rule: str) -> Checker:
    """An image map: finite values in [lo, hi], NaN where the pixel has none. A hazard of -1 read as called safe,
    and a 5 or an inf passed the HIL for `score` to refuse the saved map."""

    def check(v: Any, name: str) -> np.ndarray:
        arr = inner(v, name)
        with np.errstate(invalid="ignore"):
            bad = ~np.isnan(arr) & ~(np.isfinite(arr) & (arr >= lo) & (arr <= hi))
        if bad.any():
            raise SchemaError(f"{name}: {rule}")
        return arr

    return check


def _flags(inner: Checker) -> Checker:
    def check(v: Any, name: str) -> np.ndarray:
        arr = inner(v, name)
        if arr.size and int(arr.max()) > 1:
            raise SchemaError(f"{name}: flags must be 0 or 1")
        return arr

    return check


# Result schema revisions (docs/protocol.md, section 5.5). Grounds and flight sides are upgraded separately, and a
# decoder refuses unknown fields, so a ground announces the highest revision it decodes in
# Config.options["result_rev"] and the flight side leaves every optional Result field newer than that at its
# default (Result.for_rev), which the encoder keeps off the wire (OMIT_AT_DEFAULT). A Config without the option
# means revision 0, the baseline: the Result fields of stop 41 (its last commit 0950b5b; `git log -S` on this
# file), unchanged since elevation_unit_cm (3ba3276, 2026-12-02). A ground from before that commit refuses every
# Result anyway: psafe_step and elevation_unit_cm travel always, and their values change what the grids mean.
RESULT_FIELD_REV: dict[str, int] = {
    "elevation_filled": 1,  # stop 42, ef94408: the elevation grid's gap fills
    "skipped": 2,  # stop 43, 950eef9 on main: the stages a degraded Result left out
    "elevation_filled_image": 3,  # stop 43, df0387b on branch h2-fills, in main from c71cc53: elevation_image's fills
}
# The same revisions number the Telemetry's optional fields: a ground of an older revision refuses them too.
TELEMETRY_FIELD_REV: dict[str, int] = {
    "plan": 4,  # stop 46: the deadline plan's figures, why a stage did not run
    # stop 76: the pose refinement's outcome and the flight side's words on the pair (they reached no ground)
    "pose": 5,
    "pose_verdict": 5,
    "notes": 5,
}
# the revision this schema decodes and the reference flight side fills
RESULT_REV = max(*RESULT_FIELD_REV.values(), *TELEMETRY_FIELD_REV.values())


@dataclass(frozen=True)
class Result(Message):
    """Hazard-detection output for the pair ``frame_seqs`` (upper, lower): compact, for a serial line.

    World grid (rows toward -Y; cell ``[i, j]`` centred at ``origin_x + j * cell``, ``origin_y - i * cell``):

    * ``state_grid`` uint8: 0 safe, 1 unsafe, 2 unknown, 255 outside (``protocol.pairdir.STATE_*``);
    * ``psafe_grid`` uint8: P(safe) = v / 254 for v in 0..254, 255 = outside, on the grid decimated
      by ``psafe_step`` (block minimum: conservative);
    * ``elevation_grid`` int16 in units of ``elevation_unit_cm`` centimetres above ``elevation_offset_m``
      (-32768 = no elevation), on the grid decimated by ``elevation_step`` k: cell ``[i, j]`` is the mean
      over grid cells ``[k i : k i + k, k j : k j + k]`` (shape ``ceil(rows / k), ceil(cols / k)``);
    * ``elevation_filled`` uint8 (optional), the elevation grid's shape: 1 where the cell's elevation leans on
      a gap fill (an elevation carried into dark shadow, not matched there: any grid cell of its block).

    Full-resolution image maps (i1's pixels) only when the Config asked for them (``full_maps``);
    ``elevation_filled_image`` (optional, uint8 0/1, ``elevation_image``'s shape) marks the pixels of
    ``elevation_image`` that are gap fills, as ``elevation_filled`` does for the grid.
    Helpers to build and read these grids: :mod:`protocol.grids`.
    """

    TYPE: ClassVar[int] = 4
    OMIT_AT_DEFAULT: ClassVar[frozenset[str]] = frozenset(RESULT_FIELD_REV)
    frame_seqs: tuple = _wire(_ints(2))
    state_grid: np.ndarray = _wire(_states(_array("|u1", 2)), compress=True)
    psafe_grid: np.ndarray = _wire(_array("|u1", 2), compress=True)
    elevation_grid: np.ndarray = _wire(_array("<i2", 2), compress=True, delta=2)
    grid_origin_xy: tuple = _wire(_floats(2))
    grid_cell_m: float = _wire(_cell_size)
    elevation_step: int = _wire(_int(1, 1024), 1)
    elevation_offset_m: float = _wire(_float(), 0.0)
    elevation_unit_cm: int = _wire(_int(1, 1000), 1)
    psafe_step: int = _wire(_int(1, 1024), 1)
    sites: list = _wire(_sites, factory=list)
    no_site_reason: str | None = _wire(_optional(_str(256)), None)
    degraded: bool = _wire(_bool, False)
    level: str = _wire(_str(64), "full")
    skipped: tuple = _wire(_names(MAX_SKIPPED), factory=tuple)
    hazard_image: np.ndarray | None = _wire(
        _optional(
            _values_or_nan(_array("<f4", 2), 0.0, 1.0, "values must lie in [0, 1] or be NaN outside the covered area")
        ),
        None,
        compress=True,
    )
    elevation_image: np.ndarray | None = _wire(
        _optional(_values_or_nan(_array("<f4", 2), -np.inf, np.inf, "holds inf; NaN marks a pixel without a value")),
        None,
        compress=True,
    )
    state_image: np.ndarray | None = _wire(_optional(_states(_array("|u1", 2))), None, compress=True)
    elevation_filled: np.ndarray | None = _wire(_optional(_flags(_array("|u1", 2))), None, compress=True)
    elevation_filled_image: np.ndarray | None = _wire(_optional(_flags(_array("|u1", 2))), None, compress=True)

    def for_rev(self, rev: int) -> Result:
        """This Result as a ground that decodes revision ``rev`` can take it: every field newer than ``rev``
        (``RESULT_FIELD_REV``) at its default, hence off the wire."""
        drop = {f.name: _default_of(f) for f in fields(self) if RESULT_FIELD_REV.get(f.name, 0) > rev}
        return replace(self, **drop) if drop else self

    def check_consistency(self) -> None:
        shape = np.shape(self.state_grid)
        kp = int(self.psafe_step)
        want_p = tuple(-(-s // kp) for s in shape)
        if np.shape(self.psafe_grid) != want_p:
            raise SchemaError(
                f"Result.psafe_grid: shape {np.shape(self.psafe_grid)} != state_grid {shape} "
                f"decimated by {kp} = {want_p}"
            )
        k = int(self.elevation_step)
        want = tuple(-(-s // k) for s in shape)
        if np.shape(self.elevation_grid) != want:
            raise SchemaError(
                f"Result.elevation_grid: shape {np.shape(self.elevation_grid)} != state_grid {shape} "
                f"decimated by {k} = {want}"
            )
        if self.elevation_filled is not None and np.shape(self.elevation_filled) != want:
            raise SchemaError(
                f"Result.elevation_filled: shape {np.shape(self.elevation_filled)} != elevation_grid {want}"
            )
        self._check_sites(shape)
        images = [a for a in (self.hazard_image, self.elevation_image, self.state_image) if a is not None]
        if any(np.shape(a) != np.shape(images[0]) for a in images):
            raise SchemaError("Result: full-resolution image maps must share one shape")
        if self.elevation_filled_image is not None:  # a fill mask marks pixels of elevation_image: it needs one
            got = np.shape(self.elevation_filled_image)
            if self.elevation_image is None:
                raise SchemaError(f"Result.elevation_filled_image: shape {got} sent without elevation_image")
            if got != np.shape(self.elevation_image):
                raise SchemaError(
                    f"Result.elevation_filled_image: shape {got} != elevation_image {np.shape(self.elevation_image)}"
                )

    def _check_sites(self, shape: tuple[int, ...]) -> None:
        """A site is a spot of the mapped ground: it lies on the grid (its cells' outer edges, one cell of slack).
        One far outside was accepted and recorded with a P(safe) no cell of the grid supports."""
        if not self.sites:
            return
        rows, cols = (int(shape[0]), int(shape[1])) if len(shape) == 2 else (0, 0)
        ox, oy = (float(v) for v in self.grid_origin_xy)
        c = float(self.grid_cell_m)
        x0, x1 = ox - 1.5 * c, ox + (cols + 0.5) * c
        y0, y1 = oy - (rows + 0.5) * c, oy + 1.5 * c
        for i, s in enumerate(self.sites):
            if not (x0 <= s.x <= x1 and y0 <= s.y <= y1):
                raise SchemaError(
                    f"Result.sites[{i}]: ({s.x:.6g}, {s.y:.6g}) m is off the grid, which spans x {x0:.6g}..{x1:.6g} "
                    f"and y {y0:.6g}..{y1:.6g} m"
                )


MAX_RSS_BYTES = 1 << 50  # 1 PiB: a peak memory past it is no measurement (2**62 was printed as it came)


@dataclass(frozen=True)
class Telemetry(Message):
    """Timing and resource report for one processed pair (``stages[name] = {wall_s, cpu_s}``).

    ``plan`` (revision 4, optional) holds the figures the flight side's deadline plan decided on, numbers only
    (docs/protocol.md lists the reference flight side's keys: why a DEM stage did not run).

    Revision 5 (optional): ``pose`` holds the relative-pose refinement's figures (inliers, reprojection error, the
    correction applied; numbers only), ``pose_verdict`` its outcome in one word (the reference's are
    ``flight_sw.pose_refine.VERDICTS``; "" when none ran), and ``notes`` the flight side's warnings on the pair
    (a pose kept at navigation and why, sensors that disagree, sites withheld), which had reached no ground.
    """

    TYPE: ClassVar[int] = 5
    OMIT_AT_DEFAULT: ClassVar[frozenset[str]] = frozenset(TELEMETRY_FIELD_REV)
    frame_seqs: tuple = _wire(_ints(2))
    stages: dict = _wire(_stages, factory=dict)
    queue_wait_s: float = _wire(_duration, 0.0)
    total_latency_s: float = _wire(_duration, 0.0)
    cpu_fraction: float = _wire(_float(finite=False), float("nan"))
    peak_rss_bytes: int = _wire(_int(0, MAX_RSS_BYTES), 0)
    deadline_s: float = _wire(_float(finite=False), float("nan"))
    deadline_met: bool = _wire(_bool, True)
    link: dict = _wire(_number_dict, factory=dict)
    plan: dict = _wire(_number_dict, factory=dict)
    pose: dict = _wire(_number_dict, factory=dict)
    pose_verdict: str = _wire(_str(32), "")
    notes: tuple = _wire(_names(MAX_NOTES, MAX_NOTE_CHARS), factory=tuple)
    # the measurements a decoded Telemetry left out (they read as their defaults): a board that does not report its
    # compute latency must not read as "flight 0.00 s", the whole latency then put on the link (QA of stop 73)
    omitted: ClassVar[tuple[str, ...]] = ()
    MEASURED: ClassVar[tuple[str, ...]] = ("total_latency_s", "queue_wait_s", "cpu_fraction", "peak_rss_bytes")

    @classmethod
    def from_wire(cls, d: Any) -> Message:
        msg = super().from_wire(d)
        left_out = tuple(n for n in cls.MEASURED if n not in d)
        if left_out:
            object.__setattr__(msg, "omitted", left_out)
        return msg

    def for_rev(self, rev: int) -> Telemetry:
        """As :meth:`Result.for_rev`: every field newer than ``rev`` (``TELEMETRY_FIELD_REV``) at its default."""
        drop = {f.name: _default_of(f) for f in fields(self) if TELEMETRY_FIELD_REV.get(f.name, 0) > rev}
        return replace(self, **drop) if drop else self


@dataclass(frozen=True)
class Heartbeat(Message):
    TYPE: ClassVar[int] = 6
    time_s: float = _wire(_float())
    counter: int = _wire(_int(), 0)


@dataclass(frozen=True)
class Error(Message):
    """A failure report; ``seq`` names the offending frame (``Frame.seq``) if any."""

    TYPE: ClassVar[int] = 7
    code: str = _wire(_str(64))
    text: str = _wire(_str(MAX_TEXT))
    seq: int | None = _wire(_optional(_int(0, 2**32 - 1)), None)


MESSAGE_TYPES: dict[int, type[Message]] = {
    cls.TYPE: cls for cls in (Hello, Config, Frame, Result, Telemetry, Heartbeat, Error)
}
MESSAGE_NAMES: dict[int, str] = {code: cls.__name__ for code, cls in MESSAGE_TYPES.items()}  # for reasons and logs


def message_class(type_code: int) -> type[Message]:
    try:
        return MESSAGE_TYPES[type_code]
    except KeyError:
        raise SchemaError(f"unknown message type code {type_code}") from None


MsgT = TypeVar("MsgT", bound=Message)


def without_arrays(msg: MsgT) -> MsgT:
    """``msg`` with every array field emptied (dtype and rank kept) and the rest as it was: what the record of a
    message already handled keeps. The HIL server and the ground held every pair's images (twice) and grids until
    the run ended, +0.7-3.4 MiB a pair without bound (stop 63's soak QA). Not for the wire: an empty image or grid
    fails the schema."""
    m: Any = msg  # every message class is a dataclass (the base only declares the wire methods)
    empty = {
        f.name: np.zeros((0,) * v.ndim, v.dtype)
        for f in fields(m)
        if f.init and isinstance(v := getattr(m, f.name), np.ndarray)
    }
    return replace(m, **empty) if empty else msg
