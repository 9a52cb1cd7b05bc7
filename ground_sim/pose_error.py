"""Pose-error injection (thesis sec. 6.3): the reported pose differs from the rendered one.

Errors, per frame: altitude (Gaussian sigma and/or uniform +-bound, thesis 6.3.1 uses
uniform [-0.5, 0.5] m), pitch-plane attitude (rotation about the camera x axis, i.e. in the
plane of the surface normal and the optical axis, thesis 6.3.2; ``equal_pitch`` applies the
same draw to both frames as the thesis did), roll/yaw (about camera z / y) and lateral
(horizontal position). ``sample(rng)`` draws a :class:`PoseDelta`; ``PoseDelta.apply(pose)``
gives the reported pose.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ground_sim.errors import PoseErrorSpecError
from protocol.errors import comma_items
from protocol.pairdir import Pose


def _rot(axis: int, ang: float) -> np.ndarray:
    c, s = math.cos(ang), math.sin(ang)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


MAX_ANGLE_DEG = 45.0  # attitude error bound of a pose-error spec
MAX_OFFSET_M = 10_000.0  # altitude and lateral error bound


@dataclass(frozen=True)
class PoseDelta:
    """A realised error: reported = true + these offsets (metres, degrees)."""

    dz_m: float = 0.0
    dx_m: float = 0.0
    dy_m: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    yaw_deg: float = 0.0

    def apply(self, pose: Pose) -> Pose:
        """Reported pose: centre shifted, attitude ``R' = Rx(pitch) Ry(yaw) Rz(roll) R`` (camera axes)."""
        Rd = (
            _rot(0, math.radians(self.pitch_deg))
            @ _rot(1, math.radians(self.yaw_deg))
            @ _rot(2, math.radians(self.roll_deg))
        )
        return Pose(pose.position + np.array([self.dx_m, self.dy_m, self.dz_m]), Rd @ pose.R, pose.time_s)

    def to_dict(self) -> dict:
        return asdict(self)


def _limit(field: str) -> float:
    """The largest value of a :class:`PoseError` field: beyond it the "error" is no longer a navigation error (and
    1e308 overflows the sampler)."""
    return MAX_ANGLE_DEG if field.endswith("_deg") else MAX_OFFSET_M


def _in_range(field: str, v: float) -> bool:
    return math.isfinite(v) and 0 <= v <= _limit(field)


@dataclass(frozen=True)
class PoseError:
    """Distribution of pose errors (all zero = perfect knowledge)."""

    altitude_sigma_m: float = 0.0
    altitude_uniform_m: float = 0.0
    pitch_sigma_deg: float = 0.0
    pitch_uniform_deg: float = 0.0
    equal_pitch: bool = True
    roll_yaw_sigma_deg: float = 0.0
    lateral_sigma_m: float = 0.0

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if k == "equal_pitch":
                continue
            if not _in_range(k, v):
                raise PoseErrorSpecError(f"pose error {k} must be a number in [0, {_limit(k):g}], got {v}")

    def _one(self, rng: np.random.Generator, pitch: float) -> PoseDelta:
        dz = rng.normal(0.0, self.altitude_sigma_m) if self.altitude_sigma_m else 0.0
        if self.altitude_uniform_m:
            dz += rng.uniform(-self.altitude_uniform_m, self.altitude_uniform_m)
        lat = rng.normal(0.0, self.lateral_sigma_m, 2) if self.lateral_sigma_m else np.zeros(2)
        ry = rng.normal(0.0, self.roll_yaw_sigma_deg, 2) if self.roll_yaw_sigma_deg else np.zeros(2)
        return PoseDelta(float(dz), float(lat[0]), float(lat[1]), pitch, float(ry[0]), float(ry[1]))

    def _pitch(self, rng: np.random.Generator) -> float:
        p = rng.normal(0.0, self.pitch_sigma_deg) if self.pitch_sigma_deg else 0.0
        if self.pitch_uniform_deg:
            p += rng.uniform(-self.pitch_uniform_deg, self.pitch_uniform_deg)
        return float(p)

    def sample(self, rng: np.random.Generator) -> tuple[PoseDelta, PoseDelta]:
        """One delta per frame of a pair (upper, lower)."""
        d = self.sample_n(rng, 2)
        return d[0], d[1]

    def sample_n(self, rng: np.random.Generator, n: int) -> tuple[PoseDelta, ...]:
        """One delta per frame of an n-frame descent (the same draws as :meth:`sample` for n = 2)."""
        p0 = self._pitch(rng)
        pitches = [p0] + [p0 if self.equal_pitch else self._pitch(rng) for _ in range(n - 1)]
        return tuple(self._one(rng, p) for p in pitches)

    def apply(self, pose: Pose, rng: np.random.Generator) -> Pose:
        """Reported version of a single pose."""
        return self._one(rng, self._pitch(rng)).apply(pose)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def parse(cls, text: str) -> PoseError:
        """``alt=0.5,alt_sigma=0,pitch=0.05,pitch_sigma=0,roll_yaw=0,lateral=0,equal_pitch=1``."""
        names = {
            "alt": "altitude_uniform_m",
            "alt_sigma": "altitude_sigma_m",
            "pitch": "pitch_uniform_deg",
            "pitch_sigma": "pitch_sigma_deg",
            "roll_yaw": "roll_yaw_sigma_deg",
            "lateral": "lateral_sigma_m",
            "equal_pitch": "equal_pitch",
        }
        kw: dict = {}
        for item in comma_items(text, "--pose-error"):
            key, sep, val = item.partition("=")
            if not sep or key.strip() not in names:
                raise PoseErrorSpecError(f"--pose-error: bad item {item!r}; use key=value with keys {', '.join(names)}")
            try:
                v = float(val)
            except ValueError:
                raise PoseErrorSpecError(f"--pose-error: {key}={val!r} is not a number") from None
            if names[key.strip()] in kw:  # the last one silently won
                raise PoseErrorSpecError(f"--pose-error: {key.strip()} is given twice in {text!r}")
            if key.strip() == "equal_pitch" and v not in (0.0, 1.0):  # a flag: 5 read as "on"
                raise PoseErrorSpecError(f"--pose-error: equal_pitch is 0 or 1, got {val.strip()!r}")
            field = names[key.strip()]
            if field != "equal_pitch" and not _in_range(field, v):  # named as typed, not by the field behind it
                unit = "deg" if field.endswith("_deg") else "m"
                raise PoseErrorSpecError(
                    f"--pose-error: {key.strip()}={val.strip()} must be a number in [0, {_limit(field):g}] {unit}"
                )
            kw[names[key.strip()]] = bool(v) if key.strip() == "equal_pitch" else v
        return cls(**kw)
