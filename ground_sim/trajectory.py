"""Descent trajectories: lists of image pairs (upper frame at h, lower at ~h/2).

* ``vertical`` (thesis sec. 6.1): nadir pairs h -> h/2 above the landing site (origin),
  h in {1000, 800, 600, 400, 300, 200, 150, 100} m.
* ``approach`` (thesis sec. 2.1/6.2, Chang'e-3-like): 45 deg descent path toward the site
  (heading +Y), lander pitch 9 deg and camera line of sight offset 40 deg, so the camera is
  49 deg off nadir; pairs 2400/1200 ... 500/250. For 300/150 and 250/125 the lander attitude
  is aligned with the surface normal (pitch 0) while the 40 deg sensor offset remains: the
  thesis's epipole then moves above the image centre (sec. 6.2), which a nadir camera on a
  45 deg path could not show.
* a TOML/JSON file: ``{"pairs": [{"label": .., "altitude_m": .., "frames": [{"position_m":
  [x,y,z], "off_nadir_deg": t, "heading_deg": h} | {"position_m", "R_world_to_cam"}, ...]}]}``
  with 2-16 frames per entry, ordered by time (each lower than the one before); a frame's ``time_s`` is
  optional (0 s where another frame of the entry gives one; where none does, the times follow the velocity
  profile below over the frames' heights, as on the vertical descent).
* :func:`frames_at`: one multi-frame entry of a built-in scenario at chosen altitudes
  (``render --frames 300,250,200,150``), frame 0 the highest.

Pairs are labelled "upper/lower"; ``altitude_m`` is the LOWER altitude - the altitude the
thesis Tables 6.1 and 6.8 list (600->300 is the 300 m row, 2400->1200 the 1200 m row).
Frame times come from a velocity profile along the path: speed ``v = v_min + k s`` with
``s`` the remaining path length, so ``t(s) = ln((v_min + k s0) / (v_min + k s)) / k``.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path

import numpy as np

from ground_sim.errors import TrajectoryError
from ground_sim.geometry import border_rays, look_rotation, sky_problem
from protocol.errors import InputError
from protocol.pairdir import IMAGE_SIZE_MAX, IMAGE_SIZE_MIN, MAX_POSITION_M, Camera, Pose

VERTICAL_UPPER = (1000, 800, 600, 400, 300, 200, 150, 100)
APPROACH_PAIRS = (
    (2400, 1200, 49.0),
    (2000, 1000, 49.0),
    (1200, 600, 49.0),
    (1000, 500, 49.0),
    (600, 300, 49.0),
    (500, 250, 49.0),
    (300, 150, 40.0),
    (250, 125, 40.0),
)
V_MIN, K_DECEL = 1.0, 0.05


MAX_FRAMES = 16
MAX_ALTITUDE_M = 50_000.0  # a 512 px thesis camera sees 53 m per pixel there; the pair reader stops at 100
RENDER_FILES = ("manifest.json", "contact.png")  # render_scenario writes these beside the pair directories
# The renderer pads its terrain height bounds by 6+ m around the ground (render.plan_raster): a camera only a
# few metres up sees those bounds within centimetres, so the finest raster cell and the tile count explode
# (2,1 ran for minutes, growing memory). Measured 2026-12 on 2 cores, one 512 px nadir view of `thesis`, seed 0,
# supersample 2, tiles: 30 m 2.7 s, 25 m 3.2 s, 22 m 18 s, 20 m 13 s, 18 m and 15 m over 60 s (a cliff); at 30 m
# highland 16 s and the approach's 40 deg view 29 s. The floor sits at 30 m, above the cliff with margin.
MIN_ALTITUDE_M = 30.0


@dataclass(frozen=True)
class PairSpec:
    """2-16 frames of a descent (frame 0 highest); ``altitude_m`` is the last (lowest) frame's altitude."""

    label: str
    altitude_m: float
    poses: tuple[Pose, ...]
    camera: Camera
    scenario: str = "custom"


def _time(s0: float, s: float) -> float:
    return math.log((V_MIN + K_DECEL * s0) / (V_MIN + K_DECEL * s)) / K_DECEL


def _label(hu: float, hl: float) -> str:
    return f"{hu:g}/{hl:g}"


def vertical(camera: Camera | None = None) -> list[PairSpec]:
    cam = camera or Camera.thesis()
    R = look_rotation(0.0)
    s0 = float(VERTICAL_UPPER[0])
    return [
        PairSpec(
            _label(h, h / 2),
            h / 2,
            (Pose(np.array([0.0, 0.0, h]), R, _time(s0, h)), Pose(np.array([0.0, 0.0, h / 2]), R, _time(s0, h / 2))),
            cam,
            "vertical",
        )
        for h in VERTICAL_UPPER
    ]


def approach(camera: Camera | None = None) -> list[PairSpec]:
    cam = camera or Camera.thesis()
    s0 = APPROACH_PAIRS[0][0] * math.sqrt(2)
    out = []
    for hu, hl, tilt in APPROACH_PAIRS:
        R = look_rotation(tilt, 0.0)
        pu, pl = (Pose(np.array([0.0, -h, h]), R, _time(s0, h * math.sqrt(2))) for h in (hu, hl))
        poses = (pu, pl)
        out.append(PairSpec(_label(hu, hl), float(hl), poses, cam, "approach"))
    return out


def _approach_pose(h: float, tilt: float | None = None) -> Pose:
    """Approach path pose at altitude h: on the 45 deg line toward the site, 49 deg off nadir above 300 m."""
    s0 = APPROACH_PAIRS[0][0] * math.sqrt(2)
    t = (40.0 if h <= 300.0 else 49.0) if tilt is None else tilt
    return Pose(np.array([0.0, -h, h]), look_rotation(t, 0.0), _time(s0, h * math.sqrt(2)))


def frames_at(scenario: str, altitudes: list[float], camera: Camera | None = None) -> PairSpec:
    """One multi-frame entry of ``vertical`` or ``approach`` with frames at these altitudes (m, decreasing).

    Vertical: nadir above the site. Approach: on the 45 deg path, 49 deg off nadir above 300 m and
    40 deg at and below it (the lander aligned with the surface normal, as the thesis's last two pairs).
    """
    alts = [float(a) for a in altitudes]
    if not 2 <= len(alts) <= MAX_FRAMES:
        raise TrajectoryError(f"--frames: need 2-{MAX_FRAMES} altitudes, got {len(alts)}")
    if not all(math.isfinite(a) for a in alts):  # NaN failed the order test and was called "not decreasing"
        raise TrajectoryError(f"--frames: altitudes must be finite numbers of metres, got {alts}")
    if not all(a > 0 for a in alts) or any(b >= a for a, b in pairwise(alts)):
        raise TrajectoryError(f"--frames: altitudes must be positive and strictly decreasing, got {alts}")
    if alts[-1] < MIN_ALTITUDE_M:  # a render below it takes minutes to hours (see MIN_ALTITUDE_M)
        low = ", ".join(f"{a:g}" for a in alts if a < MIN_ALTITUDE_M)  # every one, not the lowest alone (QA of stop 84)
        raise TrajectoryError(f"--frames: altitudes must be at least {MIN_ALTITUDE_M:g} m, got {low}")
    if alts[0] > MAX_ALTITUDE_M:  # the reader refuses pixels over 100 m of ground (protocol.pairdir.scale_notes)
        raise TrajectoryError(f"--frames: altitudes must be at most {MAX_ALTITUDE_M:g} m, got {alts[0]:g}")
    cam = camera or Camera.thesis()
    if scenario == "vertical":
        s0 = float(max(VERTICAL_UPPER[0], alts[0]))
        poses = tuple(Pose(np.array([0.0, 0.0, h]), look_rotation(0.0), _time(s0, h)) for h in alts)
    elif scenario == "approach":
        poses = tuple(_approach_pose(h) for h in alts)
    else:
        raise TrajectoryError(f"--frames needs the vertical or approach scenario, got {scenario!r}")
    return PairSpec("/".join(f"{a:.10g}" for a in alts), alts[-1], poses, cam, scenario)


def _number(obj: dict, key: str, default: float, where: str) -> float:
    """``obj[key]`` as a finite float (``default`` when absent); anything else is an error naming the field."""
    v = obj.get(key, default)
    # bool is an int to Python, but `true` is no altitude; strings ("600") are refused, not parsed
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TrajectoryError(f"{where}: {key} must be a number, got {v!r:.40}")
    try:
        f = float(v)
    except OverflowError:  # an integer beyond float range (TOML/JSON allow any length)
        f = math.inf
    if not math.isfinite(f):
        raise TrajectoryError(f"{where}: {key} must be finite, got {v!r:.40}")
    return f


# a typo ("off_nadir = 20") was dropped without a word and the frame rendered looking straight down (QA of
# stop 78); scene and budget files already refused unknown keys
DOC_KEYS = ("name", "camera", "pairs")
PAIR_KEYS = ("label", "altitude_m", "frames")
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
FRAME_KEYS = ("position_m", "R_world_to_cam", "off_nadir_deg", "heading_deg", "time_s")


def _known(obj: dict, known: tuple[str, ...], where: str) -> None:
    """Refuse a key of ``obj`` that is not in ``known``, naming it and the known ones."""
    for key in obj:
        if key not in known:
            raise TrajectoryError(f"{where}: unknown key {str(key)!r:.40} (known: {', '.join(known)})")


def _frame(fr: object, where: str) -> Pose:
    if not isinstance(fr, dict):
        raise TrajectoryError(f"{where}: must be an object with position_m and R_world_to_cam or off_nadir_deg")
    _known(fr, FRAME_KEYS, where)
    both = [k for k in ("off_nadir_deg", "heading_deg") if k in fr]
    if "R_world_to_cam" in fr and both:  # the matrix won and the angles were dropped
        raise TrajectoryError(f"{where}: give R_world_to_cam or {' and '.join(both)}, not both")
    try:
        pos = np.array(fr["position_m"], dtype=float).reshape(3)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise TrajectoryError(f"{where}: position_m must be [x, y, z] in metres ({exc})") from None
    if "R_world_to_cam" in fr:
        try:
            R = np.array(fr["R_world_to_cam"], dtype=float).reshape(3, 3)
        except (TypeError, ValueError, OverflowError) as exc:
            raise TrajectoryError(f"{where}: R_world_to_cam must be a 3x3 matrix ({exc})") from None
    else:
        R = look_rotation(_number(fr, "off_nadir_deg", 0.0, where), _number(fr, "heading_deg", 0.0, where))
    check_position(pos, where)
    pose = Pose(pos, R, _number(fr, "time_s", 0.0, where))
    try:
        pose.validate(where)
    except InputError as exc:
        raise TrajectoryError(str(exc)) from None
    return pose


def check_position(pos: np.ndarray, where: str) -> None:
    """Refuse a camera position that cannot be rendered in reasonable time or processed afterwards: a
    coordinate beyond :data:`MAX_POSITION_M`, or a height under :data:`MIN_ALTITUDE_M` above the datum."""
    if not np.all(np.isfinite(pos)):
        return  # Pose.validate names non-finite values
    if float(np.abs(pos).max()) > MAX_POSITION_M:
        raise TrajectoryError(
            f"{where}: position_m {[float(v) for v in pos]} is over {MAX_POSITION_M:g} m from the origin "
            "(hazard-hil process refuses such a pair): positions are in metres"
        )
    if float(pos[2]) < MIN_ALTITUDE_M:
        raise TrajectoryError(
            f"{where}: position_m z = {float(pos[2]):g} m is below the lowest altitude render supports "
            f"({MIN_ALTITUDE_M:g} m above the datum)"
        )


def pair_dir_name(label: str) -> str:
    """The directory a pair is rendered to under the output directory (``render_scenario``'s rule)."""
    return label.replace("/", "_")


def check_distinct_dirs(labels: list[str], where: str) -> None:
    """Refuse labels that would be rendered to one directory: the later pair would overwrite the earlier."""
    seen: dict[str, str] = {}
    for label in labels:
        d = pair_dir_name(label)
        if d in seen:
            same = f"label {label!r} twice" if seen[d] == label else f"labels {seen[d]!r} and {label!r}"
            raise TrajectoryError(f"{where}: {same} would be rendered to the same directory {d!r}")
        seen[d] = label


def _check_label(label: object, where: str) -> str:
    if isinstance(label, int) and not isinstance(label, bool):
        label = str(label)  # `label = 600` in TOML: the name it always had
    # the label names the pair's output directory: it must be a plain file name, not the output
    # directory itself ("", "."), its parent (".."), a file the render writes beside the pairs, or a
    # name no file system can create
    if (
        not isinstance(label, str)
        or label in ("", ".", "..", *RENDER_FILES)
        or any(ord(c) < 32 or ord(c) == 127 for c in label)  # NUL, and a newline in a directory name
        or len(label.encode()) > 255
    ):
        raise TrajectoryError(
            f"{where}: label must be a non-empty name of at most 255 bytes, without control characters, other "
            f"than {', '.join(repr(n) for n in ('.', '..', *RENDER_FILES))}, got {label!r:.40}"
        )
    return label


MAX_TRAJECTORY_BYTES = 4 << 20  # a trajectory of a thousand pairs is about 200 kB


def from_file(path: Path) -> list[PairSpec]:
    try:
        size = path.stat().st_size
        if size > MAX_TRAJECTORY_BYTES:  # read whole, a 200 MB one cost 470 MB before it was refused (QA 66b)
            raise TrajectoryError(
                f"trajectory file {path}: {size} bytes is more than a trajectory can be ({MAX_TRAJECTORY_BYTES} bytes)"
            )
        text = path.read_text()
        doc = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError, RecursionError) as exc:
        raise TrajectoryError(f"trajectory file {path}: unreadable ({exc or 'nested too deeply'})") from None
    pairs = doc.get("pairs") if isinstance(doc, dict) else None
    if not isinstance(pairs, list) or not pairs:
        raise TrajectoryError(f"trajectory file {path}: needs a non-empty 'pairs' list")
    _known(doc, DOC_KEYS, f"trajectory file {path}")
    cam = Camera.thesis()
    if "camera" in doc and not isinstance(doc["camera"], dict):  # was ignored: the 512 px camera rendered instead
        raise TrajectoryError(f"trajectory file {path}: 'camera' must be an object (width, height, fx, fy, cx, cy)")
    if isinstance(doc.get("camera"), dict):
        _known(doc["camera"], CAMERA_KEYS, f"trajectory file {path} camera")  # a lens term would go unrendered
        try:
            cam = Camera.from_dict(doc["camera"])
        except InputError as exc:
            raise TrajectoryError(f"trajectory file {path}: {exc}") from None
        lo, hi = IMAGE_SIZE_MIN, IMAGE_SIZE_MAX
        if not (lo <= cam.width <= hi and lo <= cam.height <= hi):  # as `--image-size`: a 2 px camera rendered a
            # pair `process` crashed on, and an 8192 px one ran for minutes towards 9 GB (QA 66b)
            raise TrajectoryError(
                f"trajectory file {path}: camera of {cam.width}x{cam.height} px; render draws {lo}..{hi} px a side"
            )
    out = []
    for i, p in enumerate(pairs):
        where = f"trajectory file {path} pair #{i}"
        if not isinstance(p, dict) or not isinstance(p.get("frames"), list) or not 2 <= len(p["frames"]) <= MAX_FRAMES:
            raise TrajectoryError(f"{where}: needs 'frames' with 2-{MAX_FRAMES} frames")
        _known(p, PAIR_KEYS, where)
        poses = tuple(_frame(fr, f"{where} frame {k}") for k, fr in enumerate(p["frames"]))
        # every frame at 0 s read as frames taken at one time (a note on every such pair; QA of stop 74)
        if not any(isinstance(fr, dict) and "time_s" in fr for fr in p["frames"]):
            z0 = float(poses[0].position[2])
            poses = tuple(replace(q, time_s=_time(z0, float(q.position[2]))) for q in poses)
        for k in range(1, len(poses)):
            if not poses[k].position[2] < poses[k - 1].position[2]:
                raise TrajectoryError(f"{where}: frame {k} must be below frame {k - 1}")
            if poses[k].time_s < poses[k - 1].time_s:  # said by the pair's check, naming no file (QA of stop 73)
                raise TrajectoryError(
                    f"{where}: frame {k} is earlier than frame {k - 1} (time_s {poses[k].time_s:g} vs "
                    f"{poses[k - 1].time_s:g})"
                )
        for k, pose in enumerate(poses):  # the renderer said it of no pair or frame
            sky = sky_problem(border_rays(cam, pose))
            if sky is not None:
                raise TrajectoryError(f"{where} frame {k}: {sky}")
        hl = _number(p, "altitude_m", float(poses[-1].position[2]), where)
        if not hl > 0:  # the table row a pair is scored in: an altitude above the reference plane
            raise TrajectoryError(f"{where}: altitude_m must be positive, got {hl:g}")
        default_label = "/".join(f"{round(q.position[2], 1):g}" for q in poses)
        label = _check_label(p.get("label", default_label), where)
        out.append(PairSpec(label, hl, poses, cam, str(doc.get("name", path.stem))))
    check_distinct_dirs([s.label for s in out], f"trajectory file {path}")
    return out


def load_trajectory(spec: str | Path, camera: Camera | None = None) -> list[PairSpec]:
    """``vertical``, ``approach`` or a TOML/JSON trajectory file; ``camera`` overrides the built-in one."""
    if str(spec) == "vertical":
        return vertical(camera)
    if str(spec) == "approach":
        return approach(camera)
    path = Path(spec)
    if not path.is_file():
        if path.suffix.lower() in (".toml", ".json"):  # meant as a file: say it is not there
            raise TrajectoryError(
                f"scenario file {str(spec)!r} not found ({'a directory' if path.is_dir() else 'no such file'})"
            )
        raise TrajectoryError(f"unknown scenario {str(spec)!r}: use vertical, approach or a .toml/.json file")
    specs = from_file(path)
    return [replace(s, camera=camera) for s in specs] if camera is not None else specs
