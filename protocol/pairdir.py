"""The pair directory: 2-16 descent images, their poses and optional ground truth.

This is the offline exchange format between ``ground_sim`` (writer) and
``flight_sw`` (reader), and the way users bring their own images (docs/design.md)::

    pair.json              {"format": "sfm-hd-pair/1", "camera": {...},
                            "frames": [{"image", "position_m", "R_world_to_cam" | "q_world_to_cam",
                                        "time_s", "altimeter_m"?}, ... 2 to 16],
                            "sun": {"azimuth_deg", "elevation_deg"}}   # sun optional
    i1.png, i2.png, ...    gray images; frame 0 is the highest (earliest), frames ordered by time
    gt_elevation_i1.npy    optional float32 HxW, world Z seen by each pixel of i1
    gt_depth_i1.npy        optional float32 HxW, camera-1 z-depth
    gt_shadow_i1.npy       optional bool HxW, pixel of i1 not directly lit
    gt_hazard_i1.npy       optional float32 HxW in [0,1], ground-truth hazard (DESIGN.md rules)

Conventions: world Z up; camera frame is OpenCV's (x right, y down, z forward);
a pose is the centre ``C`` (world) and ``R`` (world->camera), so
``X_cam = R (X_world - C)``. Extra top-level keys in ``pair.json`` (for example
the true poses behind injected pose errors) are kept in :attr:`Pair.meta`.

Reading is defensive, because users bring these directories: ``pair.json`` is
size-limited before it is parsed, image paths must stay inside the directory,
image sizes are read from the file header and checked against the camera
before anything is decoded, colour and 16-bit images are converted (with a
note in :attr:`Pair.notes`), a rotation off orthonormal by up to
:data:`ORTHONORMAL_TOL` is re-orthonormalised (with a note), quaternions are
accepted, and geometry that cannot see the ground is refused. Every problem is
one :class:`PairFormatError` line naming the file. What is legal but likely makes
the maps meaningless (an implausible scale, a 16-bit frame the common shift
leaves with a few grey levels) is in :attr:`Pair.warnings`.
"""

from __future__ import annotations

import glob
import json
import math
import os
import re
import shutil
import stat
import struct
import time
import tokenize
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from protocol.errors import InputError, os_error_text

FORMAT = "sfm-hd-pair/1"
MIN_FRAMES, MAX_FRAMES = 2, 16
MAX_PAIR_JSON_BYTES = 1 << 20  # a pair.json of many frames is a few kB
MAX_MANIFEST_BYTES = 16 << 20  # a manifest of 10000 pairs is about 1 MB
MAX_IMAGE_SIDE = 8192
IMAGE_SIZE_MIN, IMAGE_SIZE_MAX = 32, 4096  # the square cameras `render` and `run --image-size` make
THESIS_CAMERA_PX = 512  # the thesis camera's side (Table 2.2)
ORTHONORMAL_TOL = 1e-3  # max |R R^T - I| re-orthonormalised with a note; beyond it: an error
MIN_DEPRESSION_DEG = 10.0  # the optical axis must point at least this far below the horizon
# an altimeter reading vs. the range to the datum along the optical axis (check_altimeter)
ALTIMETER_MAX_RATIO, ALTIMETER_SLACK_M, ALTIMETER_MAX_OFF_M = 2.0, 100.0, 5000.0

# state.npy codes (DESIGN.md): every tool that writes or scores three-state maps uses these
STATE_SAFE, STATE_UNSAFE, STATE_UNKNOWN, STATE_OUTSIDE = 0, 1, 2, 255

# The flight software's limits, here so that every tool that writes or reads a pair applies the same ones
MAX_FOCAL_SIDES = 1000.0  # focal length at most 1000 image sides (a 0.06 deg field of view)
# and at least 0.05 of its side (a 169 deg field of view; the thesis camera's is 1.87, 30 deg): fx = 1e-300 was
# mapped, with a screen of numpy overflow warnings and exit 0 (QA of stop 71)
MIN_FOCAL_SIDES = 0.05
MAX_PRINCIPAL_SIDES = 10.0  # principal point within 10 image sides of the image
MAX_POSITION_M = 1.0e7  # 10,000 km: past any descent (the Moon's radius is 1,737 km)
SUN_AZIMUTH_LIMIT_DEG = 360.0  # |azimuth|; the elevation is in (0, 90]

TRUTH_FILES = {
    "elevation": "gt_elevation_i1.npy",
    "depth": "gt_depth_i1.npy",
    "shadow": "gt_shadow_i1.npy",
    "hazard": "gt_hazard_i1.npy",
}
_TRUTH_DTYPES = {"elevation": np.float32, "depth": np.float32, "shadow": np.bool_, "hazard": np.float32}
# pair.json's keys that hold truth (the renderer's): the true poses, the injected pose errors, the hazards and the
# overlap the truth gives. A pair read without its truth leaves them out: flight software never sees them (the
# flight side's read refused a pair over a malformed true_frames, which it has no use for; QA of stop 73)
TRUTH_META_KEYS = ("true_frames", "pose_error", "hazards_in_scene_pct", "hazard_fraction", "overlap_pct")


class PairFormatError(InputError):
    """A pair directory or its contents violate the pair format."""


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics, ``K = [[fx,0,cx],[0,fy,cy],[0,0,1]]`` (thesis eq. 3.2)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def thesis(cls, size: int = THESIS_CAMERA_PX) -> Camera:
        """The thesis camera (Table 2.2, eq. 3.16): 512x512, 30 deg FOV; ``size``: that FOV on a size x size sensor
        (``f = size / 2 / tan 15 deg``, the principal point at the centre), as `run --image-size` and `evaluate
        --camera-px` render."""
        f = (size / 2.0) / math.tan(math.radians(15.0))  # 955.405 px at 512
        c = (size - 1) / 2.0
        return cls(size, size, f, f, c, c)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict[str, float | int]:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        if not isinstance(d, dict):
            raise PairFormatError(f"camera: expected an object with width, height, fx, fy, cx, cy, got {d!r:.60}")
        try:
            w, h = (_whole(d[k], k) for k in ("width", "height"))
            cam = cls(w, h, *(float(_number(d[k], k)) for k in ("fx", "fy", "cx", "cy")))
        except KeyError as exc:  # "('fx')" read as Python's, not the format's (QA of stop 84)
            raise PairFormatError(f"camera: need width, height, fx, fy, cx, cy (missing {exc})") from None
        except (TypeError, ValueError, OverflowError) as exc:
            raise PairFormatError(f"camera: need width, height, fx, fy, cx, cy ({exc})") from None
        cam.validate()
        return cam

    def validate(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not (0 < self.width <= MAX_IMAGE_SIDE and 0 < self.height <= MAX_IMAGE_SIDE):
            raise PairFormatError(
                f"camera: size must be 1..{MAX_IMAGE_SIDE} px per side, got {self.width}x{self.height}"
            )
        if not all(math.isfinite(v) for v in vals) or self.fx <= 0 or self.fy <= 0:
            raise PairFormatError(f"camera: focal lengths must be finite and positive, got {vals}")
        # bounds past any real camera, said by the reader before a note blames the positions' units for them
        side = float(max(self.width, self.height))
        if max(self.fx, self.fy) > MAX_FOCAL_SIDES * side:
            raise PairFormatError(
                f"camera: focal length {max(self.fx, self.fy):.4g} px is over {MAX_FOCAL_SIDES:g} image sides"
            )
        for name, f, n in (("fx", self.fx, self.width), ("fy", self.fy, self.height)):
            if f < MIN_FOCAL_SIDES * n:
                fov = math.degrees(2.0 * math.atan(0.5 / MIN_FOCAL_SIDES))
                raise PairFormatError(
                    f"camera: {name} {f:.4g} px is under {MIN_FOCAL_SIDES:g} of the image's {n} px (a field of view "
                    f"over {fov:.0f} deg, which no pinhole camera has)"
                )
        lim = MAX_PRINCIPAL_SIDES * side
        if not (-lim <= self.cx <= self.width + lim and -lim <= self.cy <= self.height + lim):
            raise PairFormatError(
                f"camera: principal point ({self.cx:.4g}, {self.cy:.4g}) lies more than {MAX_PRINCIPAL_SIDES:g} "
                "image sides outside the image"
            )


def _number(v: Any, name: str) -> Any:
    """``v`` if it is a JSON number; ValueError for a string, a bool or anything else (float() took "150" and true
    for a position, so a hand-edited pair.json with quoted numbers passed unnoticed)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {v!r:.40}")
    return v


def _whole(v: Any, name: str) -> int:
    """``v`` as an int if it is a whole JSON number (512 or 512.0); ValueError otherwise (128.5 px was truncated)."""
    x = _number(v, name)
    if isinstance(x, (float, np.floating)) and not float(x).is_integer():
        raise ValueError(f"{name} must be a whole number, got {x!r}")
    return int(x)


def _numbers(v: Any, name: str) -> np.ndarray:
    """A (nested) list of JSON numbers as a float array; ValueError naming ``name`` for anything else."""
    if not isinstance(v, (list, tuple)):
        raise ValueError(f"{name} must be a list of numbers, got {v!r:.40}")
    flat: list[Any] = []
    stack = [v]
    while stack:
        for item in stack.pop():
            (stack.append if isinstance(item, (list, tuple)) else flat.append)(item)
    for item in flat:
        _number(item, f"{name} entries")
    try:
        return np.array(v, dtype=float)
    except ValueError:  # rows of unequal length: numpy's "inhomogeneous shape" was the whole message (QA of stop 85)
        raise ValueError(f"{name} has rows of unequal length: {v!r:.60}") from None


# a frame this close to the datum is a camera lying on the ground: its positions are in km, not m (the 1 mm per
# pixel floor alone let km pass for cameras under ~300 px)
MIN_ALTITUDE_M = 1.0
QUATERNION_NORM_TOL = 1e-3  # a quaternion written with four decimals is normalised; further off is an error


def quaternion_to_matrix(q: Any) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``[w, x, y, z]`` (Hamilton, scalar first).

    In the pair format ``q_world_to_cam`` rotates world vectors into the camera
    frame, exactly like ``R_world_to_cam``. The quaternion is normalised first.
    """
    a = np.asarray(q, dtype=np.float64).reshape(4)
    n = float(np.linalg.norm(a))
    if not math.isfinite(n) or n < 1e-9:
        raise PairFormatError(f"q_world_to_cam must be a finite non-zero [w, x, y, z], got {a.tolist()}")
    w, x, y, z = a / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True)
class Pose:
    """Camera centre ``position`` (world, m), rotation ``R`` (world->camera), time (s)."""

    position: np.ndarray
    R: np.ndarray
    time_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", np.asarray(self.position, dtype=np.float64).reshape(3))
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))

    def validate(self, what: str = "pose", tol: float = 1e-6) -> None:
        """Raise :class:`PairFormatError` unless finite with ``R`` a proper rotation."""
        if not (np.all(np.isfinite(self.position)) and np.all(np.isfinite(self.R)) and math.isfinite(self.time_s)):
            raise PairFormatError(f"{what}: position, rotation and time must be finite (got NaN/inf)")
        with np.errstate(over="ignore", invalid="ignore"):  # an entry of 1e308 overflows: inf is then the error
            err = float(np.abs(self.R @ self.R.T - np.eye(3)).max())
        if not err <= tol:
            raise PairFormatError(f"{what}: R_world_to_cam is not orthonormal (max |R R^T - I| = {err:.4g})")
        if np.linalg.det(self.R) < 0:
            raise PairFormatError(f"{what}: R_world_to_cam is a reflection (det < 0)")

    def orthonormalised(self, what: str = "pose", tol: float = ORTHONORMAL_TOL) -> tuple[Pose, str | None]:
        """The nearest rotation to ``R`` (polar decomposition by SVD) when ``R`` is within ``tol`` of one.

        Rotations written with a few decimals are a few 1e-4 off orthonormal;
        they are repaired and a note says so. Further off is an error.
        """
        if not (np.all(np.isfinite(self.position)) and np.all(np.isfinite(self.R)) and math.isfinite(self.time_s)):
            raise PairFormatError(f"{what}: position, rotation and time must be finite (got NaN/inf)")
        with np.errstate(over="ignore", invalid="ignore"):  # an entry of 1e308 overflows: inf is then the error
            err = float(np.abs(self.R @ self.R.T - np.eye(3)).max())
        if err <= 1e-9:
            return self, None
        if not err <= tol:
            raise PairFormatError(
                f"{what}: R_world_to_cam is not orthonormal (max |R R^T - I| = {err:.6g} > {tol:g}); "
                "give a rotation matrix or q_world_to_cam"
            )
        u, _, vt = np.linalg.svd(self.R)
        fixed = Pose(self.position, u @ vt, self.time_s)
        return fixed, f"{what}: rotation re-orthonormalised (was {err:.1e} off)"

    @property
    def optical_axis(self) -> np.ndarray:
        """Viewing direction in world coordinates (third row of R)."""
        return self.R[2].copy()

    def to_dict(self, image: str) -> dict[str, Any]:
        return {
            "image": image,
            "position_m": [float(v) for v in self.position],
            "R_world_to_cam": [[float(v) for v in row] for row in self.R],
            "time_s": float(self.time_s),
        }


@dataclass(frozen=True)
class Sun:
    """Sun direction: azimuth clockwise from world +Y toward +X, elevation above horizontal (deg)."""

    azimuth_deg: float
    elevation_deg: float

    def direction(self) -> np.ndarray:
        """Unit vector from the ground toward the sun, world frame."""
        az, el = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def image_name(k: int) -> str:
    """File name of frame ``k`` (0-based): ``i1.png``, ``i2.png``, ..."""
    return f"i{k + 1}.png"


@dataclass
class Pair:
    """2-16 descent frames ordered by time; frame 0 (``i1``) is the highest and the reference.

    Tools that need exactly two images use :attr:`upper` and :attr:`lower`
    (frames 0 and -1). ``altimeter_m`` holds one slant range per frame (NaN:
    no reading). ``notes`` collects what reading had to convert or repair; ``warnings`` what it found legal but
    implausible enough to make the maps meaningless (:meth:`scale_notes`, a frame the common 16-bit shift left with
    a few grey levels: ``shallow_warnings`` holds each such frame's warning by its number, ``shallow_frames`` the
    numbers). A reader's caller records both with its outputs (``process``: result.json ``notes`` and ``warnings``).
    """

    camera: Camera
    poses: tuple[Pose, ...]
    images: tuple[np.ndarray, ...]
    sun: Sun | None = None
    truth: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    altimeter_m: tuple[float, ...] = ()
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    shallow_warnings: dict[int, str] = field(default_factory=dict)

    @property
    def shallow_frames(self) -> tuple[int, ...]:
        """The frames the common 16-bit shift left with a few grey levels (:attr:`shallow_warnings`' numbers)."""
        return tuple(sorted(self.shallow_warnings))

    def __post_init__(self) -> None:
        self.poses = tuple(self.poses)
        self.images = tuple(self.images)
        if not self.altimeter_m:
            self.altimeter_m = tuple(math.nan for _ in self.poses)
        self.altimeter_m = tuple(float(a) for a in self.altimeter_m)

    @property
    def n_frames(self) -> int:
        return len(self.images)

    @property
    def upper(self) -> tuple[np.ndarray, Pose]:
        """Frame 0: the reference image (all maps are in its pixels) and its pose."""
        return self.images[0], self.poses[0]

    @property
    def lower(self) -> tuple[np.ndarray, Pose]:
        """The last (lowest) frame and its pose: with frame 0, the pair of a two-view tool."""
        return self.images[-1], self.poses[-1]

    def validate(self) -> None:
        """Check frame count, sizes, dtypes, poses, geometry and the altitude order."""
        self.camera.validate()
        n = len(self.images)
        if not MIN_FRAMES <= n <= MAX_FRAMES or len(self.poses) != n or len(self.altimeter_m) != n:
            raise PairFormatError(
                f"need {MIN_FRAMES}-{MAX_FRAMES} frames with one pose and one altimeter value each, got "
                f"{n} images, {len(self.poses)} poses, {len(self.altimeter_m)} altimeter values"
            )
        shape = (self.camera.height, self.camera.width)
        for k, img in enumerate(self.images):
            if img.dtype != np.uint8 or img.ndim != 2:
                raise PairFormatError(f"i{k + 1}: must be 8-bit gray, got {img.dtype} with shape {img.shape}")
            if img.shape != shape:
                raise PairFormatError(
                    f"i{k + 1}: size {img.shape[1]}x{img.shape[0]} does not match the camera's {shape[1]}x{shape[0]}"
                )
        for k, pose in enumerate(self.poses):
            pose.validate(f"frame {k} pose")
            check_sees_ground(pose, f"frame {k}")
        for k in range(1, n):
            z0, z1 = self.poses[k - 1].position[2], self.poses[k].position[2]
            if not z1 < z0:
                raise PairFormatError(
                    f"frame {k} must be below frame {k - 1} (z = {z1:.3f} m vs {z0:.3f} m): frames are ordered by "
                    "time through a descent, frame 0 highest"
                )
            t0, t1 = self.poses[k - 1].time_s, self.poses[k].time_s
            if t1 < t0:
                raise PairFormatError(f"frame {k} is earlier than frame {k - 1} (time_s {t1:g} vs {t0:g})")
        for k, (a, pose) in enumerate(zip(self.altimeter_m, self.poses)):
            check_altimeter(a, pose, f"frame {k}")
        for name, arr in self.truth.items():
            if name not in TRUTH_FILES:
                raise PairFormatError(f"unknown ground-truth layer {name!r}")
            if arr.shape != shape:
                raise PairFormatError(f"ground truth {name}: shape {arr.shape} != image shape {shape}")

    def scale_notes(self) -> list[str]:
        """Warnings for geometry that is legal but implausible (e.g. positions in km, not m)."""
        out = []
        z0 = float(self.poses[0].position[2])
        for k, pose in enumerate(self.poses):  # frame 0 alone let km positions pass at 256 px (its 1.3 mm)
            z = float(pose.position[2])
            gsd = z / max(1e-9, -float(pose.R[2, 2])) / self.camera.fx
            if gsd < 1e-3 or gsd > 100.0:
                # a focal length of 0.5 px (in mm? a fraction of the width?) was blamed on the positions (QA 66)
                f = self.camera.fx
                odd_f = not 0.1 * self.camera.width <= f <= 100.0 * self.camera.width
                out.append(
                    f"frame {k} sees {gsd:.2g} m per pixel at {z:g} m altitude (expected 1 mm - 100 m per pixel): "
                    + (
                        f"the focal length fx = {f:g} px is implausible for a {self.camera.width} px wide image "
                        "(it must be in pixels)"
                        if odd_f
                        else "positions must be in metres"
                    )
                )
                break
        else:
            # a camera under 128 px sees over 1 mm per pixel even from 0.3 m: positions in km passed (QA of stop 79)
            low = min(range(len(self.poses)), key=lambda k: float(self.poses[k].position[2]))
            z = float(self.poses[low].position[2])
            if z < MIN_ALTITUDE_M:
                out.append(
                    f"frame {low} is {z:g} m above the datum (expected at least {MIN_ALTITUDE_M:g} m): positions must "
                    f"be in metres (in km, a {1000 * z:g} m altitude reads {z:g})"
                )
        base = float(np.linalg.norm(self.poses[0].position - self.poses[-1].position))
        if base < 0.01 * z0:
            out.append(
                f"the baseline between the first and last frame is {base:.3g} m, under 1 % of the altitude "
                f"({z0:g} m): there is almost no parallax to recover elevation from"
            )
        return out


def check_altimeter(altimeter_m: float, pose: Pose, what: str = "frame") -> None:
    """Refuse an altimeter reading that is not a positive range, or that no terrain can explain.

    ``altimeter_m`` is the slant range along the optical axis to the ground (NaN: no reading).
    It is compared with ``D = z / cos(off-nadir)``, the range along that axis to the datum
    plane (Z = 0) from the camera at height ``z``; ground above or below the datum moves the
    reading by its height over that cosine. The reading is refused when it differs from ``D``

    * by more than :data:`ALTIMETER_MAX_OFF_M` (5 km: more relief under one descent view than
      lunar terrain has), or
    * by more than a factor :data:`ALTIMETER_MAX_RATIO` (2) *and* more than
      :data:`ALTIMETER_SLACK_M` (100 m): ground half the camera's height above the datum, or as
      far below it as the camera is above, is a mountain or a pit, not the landing site the
      datum is at, while near the ground (a camera 20 m up over a 30 m deep crater floor) the
      factor alone would refuse real terrain.

    The renders of ``ground_sim`` (ranges to the true terrain) differ from ``D`` by tens of metres.
    A reading in km instead of m, or a 1e9 placeholder, is refused.
    """
    a = float(altimeter_m)
    if math.isnan(a):
        return
    if not (math.isfinite(a) and a > 0):
        raise PairFormatError(f"{what}: altimeter_m must be a positive range or absent, got {a}")
    z = float(pose.position[2])
    cos_off = -float(pose.R[2, 2])  # optical axis . down; check_sees_ground keeps it >= sin 10 deg
    if not (z > 0 and cos_off > 0):
        return  # check_sees_ground refuses such a pose with its own message
    d = z / cos_off
    off = abs(a - d)
    if off > ALTIMETER_MAX_OFF_M or (max(a / d, d / a) > ALTIMETER_MAX_RATIO and off > ALTIMETER_SLACK_M):
        raise PairFormatError(
            f"{what}: altimeter_m {a:g} m is implausible for a camera at z = {z:g} m (the datum is {d:.1f} m away "
            f"along the optical axis; no terrain puts the ground more than {ALTIMETER_MAX_RATIO:g}x and "
            f"{ALTIMETER_SLACK_M:g} m, or {ALTIMETER_MAX_OFF_M / 1000:g} km, from it): is the reading in metres?"
        )


def check_sees_ground(pose: Pose, what: str = "pose") -> None:
    """Refuse a camera under the reference plane or looking less than 10 deg below the horizon."""
    if not pose.position[2] > 0:
        raise PairFormatError(
            f"{what}: camera at z = {pose.position[2]:g} m is not above the reference ground plane (world Z up)"
        )
    depression = math.degrees(math.asin(max(-1.0, min(1.0, -float(pose.R[2, 2])))))
    if depression < MIN_DEPRESSION_DEG:
        raise PairFormatError(
            f"{what}: the camera looks {depression:.0f} deg below the horizon (optical axis {pose.R[2].round(3)} "
            f"in world coordinates): it cannot see the ground; need >= {MIN_DEPRESSION_DEG:g} deg "
            "(is R_world_to_cam transposed?)"
        )


def pair_fingerprint(images: Sequence[np.ndarray]) -> str:
    """A short hash of a pair's frames (their shapes and pixels): an output directory that records it can be
    told apart from one made from another pair, wherever either was moved."""
    import hashlib

    h = hashlib.sha256()
    for img in images:
        h.update(repr((img.shape, img.dtype.str)).encode())
        h.update(np.ascontiguousarray(img).tobytes())
    return h.hexdigest()[:20]


def write_pair(directory: str | Path, pair: Pair) -> Path:
    """Write ``pair`` in the DESIGN.md layout, ``pair.json`` last; returns the directory. A failed write is one
    OSError naming the file (:func:`write_pair_atomic` leaves nothing half-written)."""
    pair.validate()
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    try:
        _write_files(d, pair)
    except OSError as exc:
        raise OSError(os_error_text(exc, "write")) from None
    return d


def _write_files(d: Path, pair: Pair) -> None:
    import cv2

    names = [image_name(k) for k in range(pair.n_frames)]
    for name, img in zip(names, pair.images):
        if not cv2.imwrite(str(d / name), img):
            raise OSError(f"could not write {d / name} (no space left on the device?)")
    frames = []
    for p, n, a in zip(pair.poses, names, pair.altimeter_m):
        fr = p.to_dict(n)
        if math.isfinite(a):
            fr["altimeter_m"] = a
        frames.append(fr)
    doc: dict[str, Any] = {"format": FORMAT, "camera": pair.camera.to_dict(), "frames": frames}
    if pair.sun is not None:
        doc["sun"] = {"azimuth_deg": pair.sun.azimuth_deg, "elevation_deg": pair.sun.elevation_deg}
    for key, value in pair.meta.items():
        if key in doc:
            raise PairFormatError(f"meta key {key!r} collides with a format key")
        doc[key] = value
    for name, arr in pair.truth.items():
        path = d / TRUTH_FILES[name]
        try:
            np.save(path, np.asarray(arr, dtype=_TRUTH_DTYPES[name]))
        except OSError as exc:  # numpy's short write names neither the file nor the cause
            if exc.filename is not None:
                raise
            raise OSError(f"cannot write {path}: {exc} (no space left on the device?)") from None
    (d / "pair.json").write_text(json.dumps(doc, indent=1, sort_keys=False) + "\n")  # last: the pair is whole


def is_render_file(name: str) -> bool:
    """Whether a file name is one :func:`write_pair` writes (``pair.json``, ``iK.png``, the truth files)."""
    return name == "pair.json" or name in TRUTH_FILES.values() or re.fullmatch(r"i[1-9][0-9]*\.png", name) is not None


def is_write_leftover(name: str) -> bool:
    """Whether a directory name is the sibling a :func:`write_pair_atomic` stopped midway left (``X.partialPID``,
    ``X.oldPID``): not a pair of the render, though it may hold a ``pair.json``."""
    return re.fullmatch(r".+\.(partial|old)[0-9]+", name) is not None


# a ``.partialPID`` untouched this long is no live write (a pair is written in seconds): the PID alone cannot say,
# since a writer in another PID namespace or on another host sharing the cache has a PID meaningless here
PARTIAL_STALE_S = 600.0


def _last_touched(d: Path) -> float:
    """The latest mtime of ``d`` and the files in it (``inf`` when it cannot be read: kept)."""
    try:
        return max([d.stat().st_mtime, *(f.stat().st_mtime for f in d.iterdir())])
    except OSError:
        return math.inf


def _drop_dead_partials(d: Path) -> None:
    """Remove the ``.partialPID`` siblings of ``d`` whose writer is dead (killed outright mid-write: a rerun neither
    removed nor named them; stop 63's QA): no process here has that PID and nothing in it was written for
    :data:`PARTIAL_STALE_S` (a live writer elsewhere, another container or host on a shared cache, has a PID that
    names nothing here: review of stop 63). ``.oldPID`` ones may hold a user's files, kept."""
    try:
        siblings = list(d.parent.glob(f"{glob.escape(d.name)}.partial*"))
    except OSError:
        return
    for stale in siblings:
        m = re.fullmatch(re.escape(d.name) + r"\.partial([0-9]+)", stale.name)
        if m is None or int(m.group(1)) == os.getpid():
            continue
        try:
            os.kill(int(m.group(1)), 0)
        except ProcessLookupError:  # no such process here: its writer is gone, unless it writes from elsewhere
            if time.time() - _last_touched(stale) > PARTIAL_STALE_S:
                shutil.rmtree(stale, ignore_errors=True)
        except (PermissionError, OverflowError):  # another user's live process; a PID no process can have
            continue


def write_pair_atomic(
    directory: str | Path,
    pair: Pair,
    *,
    replace: bool = False,
    kept: list[str] | None = None,
    before_rename: Callable[[], None] | None = None,
) -> Path:
    """:func:`write_pair` into a private sibling, then renamed into place: a reader never sees a
    half-written directory. When the directory exists already, ``replace`` puts ours in its place (the old
    one is renamed aside first and removed after: a stop between the two renames leaves the old one beside,
    never a mix of both); otherwise the one there is kept and ours dropped (another process finished the
    same directory first: two studies rendering into one cache). Files of the old directory that are not
    a render's own (:func:`is_render_file`: a user's notes, a ``process --out PAIR/out``) are moved into the new
    one, not deleted, and their names added to ``kept``. A failed write (a full disk) leaves nothing and names the
    file. ``before_rename`` runs once the new directory is whole, before it takes its place (a render drops the
    earlier render's manifest there, not before a write that may fail). Returns the directory."""
    d = Path(directory)
    tmp = d.with_name(f"{d.name}.partial{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    _drop_dead_partials(d)
    try:
        write_pair(tmp, pair)
    except BaseException:  # a full disk or a Ctrl-C: no half-written sibling left behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if before_rename is not None:
        before_rename()
    old = d.with_name(f"{d.name}.old{os.getpid()}")
    moved_aside = False
    if replace and d.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(d, old)
        moved_aside = True
    try:
        os.replace(tmp, d)
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)
        if moved_aside and not d.exists():  # put the old one back: never neither
            os.replace(old, d)
            raise
        if not (d / "pair.json").is_file():
            raise
    if moved_aside:
        # the user's own files come along; a stop before the old one is removed leaves them in it, beside
        for entry in sorted(old.iterdir()):
            if not is_render_file(entry.name) and not (d / entry.name).exists():
                os.replace(entry, d / entry.name)
                if kept is not None:
                    kept.append(entry.name)
        shutil.rmtree(old, ignore_errors=True)
    return d


# --------------------------------------------------------------------------- image headers
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def image_header_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding: PNG, JPEG, PGM/PPM, BMP, TIFF.

    Lets a reader refuse a 65535 x 65535 image before it allocates anything. A
    truncated or garbled header is a :class:`PairFormatError` naming the file.
    """
    with path.open("rb") as f:
        head = f.read(64 * 1024)
    try:
        if head[:8] == PNG_MAGIC:
            if head[12:16] != b"IHDR":
                raise ValueError("PNG without an IHDR chunk")
            w, h = struct.unpack(">II", head[16:24])
            return int(w), int(h)
        if head[:2] == b"\xff\xd8":
            return _jpeg_size(path)
        if head[:2] in (b"P2", b"P5", b"P3", b"P6"):
            tokens: list[bytes] = []
            for line in head[2:].split(b"\n"):
                tokens += line.split(b"#", 1)[0].split()
                if len(tokens) >= 2:
                    # int() of bytes also takes b" 1_0" and b"+3": only plain digits are a size
                    if not (tokens[0].isdigit() and tokens[1].isdigit()):
                        w_s, h_s = (t.decode("ascii", "replace")[:20] for t in tokens[:2])
                        raise ValueError(f"PGM/PPM size {w_s!r} x {h_s!r} is not two integers")
                    return int(tokens[0]), int(tokens[1])
            raise ValueError("PGM/PPM header without a width and height")
        if head[:2] == b"BM":
            w, h = struct.unpack("<ii", head[18:26])
            return abs(int(w)), abs(int(h))
        if head[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_size(path, head)
    except (struct.error, ValueError) as exc:
        # a short read leaves struct too few bytes: the file was cut off or is not what its magic says
        detail = "header cut off" if isinstance(exc, struct.error) else str(exc)
        raise PairFormatError(f"{path}: not a readable image ({detail})") from None
    raise PairFormatError(f"{path}: not a PNG, JPEG, PGM/PPM, BMP or TIFF image")


PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel (PNG spec, sec 11.2.2)
ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def png_pixel_bytes(width: int, height: int, bits_per_pixel: int, interlaced: bool) -> int:
    """Bytes a PNG's pixel stream inflates to: ``sum over passes of rows * (1 + ceil(cols * bpp / 8))``, one
    pass for a plain image, Adam7's seven (PNG spec sec 8.2) for an interlaced one; a pass with no pixels
    has no rows at all."""
    passes = ADAM7 if interlaced else ((0, 0, 1, 1),)
    total = 0
    for x0, y0, dx, dy in passes:
        cols, rows = max(0, -(-(width - x0) // dx)), max(0, -(-(height - y0) // dy))
        if cols and rows:
            total += rows * (1 + (cols * bits_per_pixel + 7) // 8)
    return total


def png_damage(data: bytes, *, size: tuple[int, int] | None = None, inflate: bool = True) -> str | None:
    """Why the PNG bytes ``data`` cannot decode whole; None when they can, or are not a PNG.

    Checked as libpng meets them (PNG spec, W3C 2003, sec 5 and 10): IHDR first (of ``size``, width and
    height, when given), each critical chunk's CRC-32 over its type and data (libpng only warns about an
    ancillary chunk's or IEND's, and decodes on), an IDAT, and IEND. With ``inflate``, the IDAT data must also
    be one complete zlib stream of exactly :func:`png_pixel_bytes`, each row of a plain image led by a filter
    type 0-4; inflation stops one byte past that size, so a zlib bomb costs no more memory than the image it
    claims to be. libpng meets the same damage by writing its own line to the C stderr before OpenCV returns
    nothing: checked here first, the reader's one-line error is the only one."""
    import zlib

    if data[:8] != PNG_MAGIC:
        return None
    pos, z, expect, out, rows, seen_idat = 8, zlib.decompressobj(), -1, bytearray(), 0, False
    while True:
        if pos + 12 > len(data):
            return "no IEND chunk: the file is truncated"
        length, kind = struct.unpack_from(">I4s", data, pos)
        name = kind.decode("latin-1")
        end = pos + 12 + length
        if end > len(data):
            return f"chunk {name!r} cut off: the file is truncated"
        body = memoryview(data)[pos + 8 : end - 4]
        critical = not kind[0] & 0x20
        if (
            critical
            and kind != b"IEND"
            and zlib.crc32(memoryview(data)[pos + 4 : end - 4]) != struct.unpack_from(">I", data, end - 4)[0]
        ):
            return f"chunk {name!r} fails its CRC: the file is damaged"
        pos = end
        if expect < 0:
            if kind != b"IHDR" or length != 13:
                return "the first chunk is not IHDR"
            w, h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", body)
            if size is not None and (w, h) != tuple(size):
                return f"its IHDR says {w}x{h}, not {size[0]}x{size[1]}"
            if colour not in PNG_CHANNELS or interlace > 1:
                return f"colour type {colour} / interlace {interlace} is not PNG's"
            expect = png_pixel_bytes(w, h, PNG_CHANNELS[colour] * depth, bool(interlace))
            rows = 0 if interlace else h
        elif kind == b"IDAT":
            seen_idat = True
            if inflate:
                try:
                    out += z.decompress(z.unconsumed_tail + body, max(expect + 1 - len(out), 1))
                except zlib.error as exc:
                    return f"the pixel data does not inflate: {exc}"
                if len(out) > expect:
                    return f"the pixel data holds more than the {expect} bytes the header's size needs"
        elif kind == b"IEND":
            break
    if not seen_idat:
        return "no IDAT chunk: the file holds no pixels"
    if not inflate:
        return None
    if not z.eof:
        return "the pixel data stops short: its zlib stream is not complete"
    if len(out) != expect:
        return f"the pixel data holds {len(out)} bytes, the header's size needs {expect}"
    if rows and max(out[:: expect // rows]) > 4:
        return "a pixel row has an unknown filter type"
    return None


def _jpeg_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()[: 4 << 20]
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            i += 1
            continue
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = struct.unpack(">H", data[i + 2 : i + 4])[0]
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return int(w), int(h)
        i += 2 + length
    raise ValueError("JPEG without a frame header")


def _tiff_size(path: Path, head: bytes) -> tuple[int, int]:
    """TIFF width and height from the first image directory, wherever in the file it is (libtiff, and so OpenCV,
    writes it after the pixels: one seek, at most 4096 tags read); ValueError/struct.error when it is not there."""
    e = "<" if head[:2] == b"II" else ">"
    (off,) = struct.unpack(e + "I", head[4:8])
    count = struct.unpack(e + "H", head[off : off + 2])[0] if off + 2 <= len(head) else None
    if count is not None and off + 2 + 12 * count <= len(head):  # the whole directory within the head read
        ifd = head[off:]
    else:
        with path.open("rb") as f:
            f.seek(off)
            ifd = f.read(2 + 12 * 4096)
        if len(ifd) < 2:
            raise ValueError("TIFF directory beyond the end of the file")
    (n,) = struct.unpack(e + "H", ifd[:2])
    size: dict[int, int] = {}
    for k in range(n):
        p = 2 + 12 * k
        if p + 12 > len(ifd):
            break
        tag, typ = struct.unpack(e + "HH", ifd[p : p + 4])
        if tag in (256, 257):
            size[tag] = struct.unpack(e + ("H" if typ == 3 else "I"), ifd[p + 8 : p + (10 if typ == 3 else 12)])[0]
    if 256 not in size or 257 not in size:
        raise ValueError("TIFF without width/height tags")
    return int(size[256]), int(size[257])


DEEP_SCALE_SHARE = 1e-4  # 16-bit frames are scaled to 8 bits ignoring this share of their brightest pixels (>= 1)


def _bright_end(img: np.ndarray) -> int:
    """The value below which all but the brightest max(1, :data:`DEEP_SCALE_SHARE` x n) pixels lie: one hot pixel
    in a 100 px frame (its 99.99th percentile is its maximum) set the scale too (review of stop 73)."""
    flat = np.asarray(img).reshape(-1)
    k = flat.size - 1 - min(flat.size - 1, max(1, int(flat.size * DEEP_SCALE_SHARE)))
    return int(np.partition(flat, k)[k])


# a 16-bit frame the common shift leaves fewer bits than this (32 grey levels), where a shift of its own would have
# kept more, is warned: the frames' bit depths (or exposures) differ, and little in it can be matched
SHALLOW_BITS = 6


def to_gray8(
    imgs: list[np.ndarray], names: list[str], paths: Sequence[str | Path] | None = None
) -> tuple[list[np.ndarray], list[str], dict[int, str]]:
    """8-bit gray versions of decoded images, notes on what was converted, and warnings by frame.

    Colour becomes luminance (OpenCV's BT.601 weights). Deeper images are
    shifted right by the same number of bits in every frame (the bits above
    the frames' brightest but a few, :func:`_bright_end`, are unused; those
    few saturate), so the frames keep one common radiometric
    scale, which the correlation needs. A frame whose own values span so many
    fewer bits than the deepest frame's that the common shift leaves it under
    :data:`SHALLOW_BITS` (a 16-bit file of 12-bit values beside one of 16) is
    warned, naming its file: it keeps a few grey levels, which the flight
    software would otherwise call a blank image. ``names`` name the frames in
    notes, ``paths`` (default: ``names``) in errors and warnings.
    """
    import cv2

    where = [str(p) for p in (paths if paths is not None else names)]
    notes = []
    out = []
    for k, img in enumerate(imgs):
        if img.ndim == 3:
            code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(img.shape[2])
            if code is None:
                raise PairFormatError(f"{where[k]}: {img.shape[2]} channels (need gray, BGR or BGRA)")
            gray = (
                img.shape[2] == 4
                and np.array_equal(img[..., 0], img[..., 1])
                and np.array_equal(img[..., 1], img[..., 2])
            )
            # gray+alpha, which the decoder gives as BGRA: nothing was colour (QA of stop 73)
            notes.append(
                f"{names[k]}: gray with an alpha channel: the alpha left out"
                if gray
                else f"{names[k]}: colour converted to gray"
            )
            out.append(cv2.cvtColor(img, code))
        else:
            out.append(img)
    warnings: dict[int, str] = {}
    deep = [k for k, img in enumerate(out) if img.dtype != np.uint8]
    if deep:
        for k in deep:
            if out[k].dtype not in (np.uint16, np.dtype(">u2")):
                raise PairFormatError(f"{where[k]}: {out[k].dtype} pixels (need 8- or 16-bit unsigned)")
        # the scale from a high percentile, not the maximum: one hot pixel at 65535 in a 12-bit image shifted it by 8
        # bits, not 4, and left ~9 grey levels (coverage 96 % -> 41 %, no warning; QA of stop 73). The few pixels
        # above it saturate at 255 and are counted
        ends = {k: _bright_end(out[k]) for k in deep}
        top_k = max(deep, key=lambda k: ends[k])
        top = ends[top_k]
        shift = max(0, top.bit_length() - 8)
        clipped = 0
        for k in deep:
            shifted = np.right_shift(out[k].astype(np.uint16), shift)
            clipped += int(np.count_nonzero(shifted > 255))
            out[k] = np.minimum(shifted, 255).astype(np.uint8)
            own = ends[k].bit_length()
            kept = max(0, own - shift)
            # the shift took bits this frame would have kept with a shift of its own (a 12-bit frame beside a 16-bit
            # one kept 16 grey levels and was then called a blank, black or lost image; QA of stop 75)
            if kept < SHALLOW_BITS and kept < min(own, 8):
                levels = len(np.unique(out[k]))
                warnings[k] = (
                    f"{where[k]}: after the common 8-bit shift (right by {shift} bits, set by {names[top_k]}) it keeps "
                    f"only {levels} grey levels: its values span {own} bits, {names[top_k]}'s {top.bit_length()}; "
                    "a pair's 16-bit frames must share one bit depth and radiometric scale"
                )
        notes.append(
            f"16-bit images ({', '.join(names[k] for k in deep)}) shifted right by {shift} bits to 8-bit"
            + (f"; {clipped} of their brightest pixels saturated" if clipped else "")
        )
    return out, notes, warnings


# the fields the format gives a frame, the camera and the sun (DESIGN.md); anything else is said, not read
FRAME_KEYS = ("image", "position_m", "R_world_to_cam", "q_world_to_cam", "time_s", "altimeter_m")
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
SUN_KEYS = ("azimuth_deg", "elevation_deg")


def unknown_keys(obj: Any, known: Sequence[str], where: str) -> list[str]:
    """A warning for each key of ``obj`` the format does not have, with the known key it is closest to: a frame's
    ``"altimeter_range_m"`` was ignored without a word, and with it the check of the DEM against the altimeter, as
    was a camera's distortion model (QA of stop 84)."""
    import difflib

    if not isinstance(obj, dict):
        return []
    out = []
    for key in obj:
        if key in known:
            continue
        near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.5)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        shown = repr(str(key)[:60])  # repr: a key's control characters escaped, not written to a terminal
        out.append(f"{where}: {shown} is not a field of the format and was ignored{hint}; it has {', '.join(known)}")
    return out


def _load_json(path: Path) -> Any:
    size = path.stat().st_size
    if size > MAX_PAIR_JSON_BYTES:
        raise PairFormatError(f"{path}: {size} bytes is more than a pair.json can be ({MAX_PAIR_JSON_BYTES} bytes)")
    try:
        return json.loads(path.read_bytes())
    except RecursionError:
        raise PairFormatError(f"{path}: JSON nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, an integer of more than 4300 digits
        raise PairFormatError(f"{path}: not valid JSON ({str(exc)[:200]})") from None


def _frame_pose(fr: Any, k: int, meta_path: Path) -> tuple[Pose, str, float]:
    if not isinstance(fr, dict):
        raise PairFormatError(f"{meta_path}: frame {k} must be an object")
    if "R_world_to_cam" in fr and "q_world_to_cam" in fr:  # one would be ignored, and they may disagree
        raise PairFormatError(f"{meta_path}: frame {k}: give R_world_to_cam or q_world_to_cam, not both")
    try:
        if "R_world_to_cam" in fr:
            R = _numbers(fr["R_world_to_cam"], "R_world_to_cam")
            if R.shape != (3, 3):
                raise ValueError(f"R_world_to_cam has shape {R.shape}, need 3x3")
        elif "q_world_to_cam" in fr:
            q = _numbers(fr["q_world_to_cam"], "q_world_to_cam")
            if q.shape != (4,):
                raise ValueError(f"q_world_to_cam has shape {q.shape}, need 4 numbers [w, x, y, z]")
            norm = float(np.linalg.norm(q)) if q.shape == (4,) else math.nan
            if math.isfinite(norm) and abs(norm - 1.0) > QUATERNION_NORM_TOL:  # as a matrix off orthonormal
                raise PairFormatError(
                    f"{meta_path}: frame {k}: q_world_to_cam has norm {norm:.6g}; a unit quaternion is "
                    f"[w, x, y, z] with norm 1 (within {QUATERNION_NORM_TOL:g})"
                )
            R = quaternion_to_matrix(q)
        else:
            raise KeyError("R_world_to_cam or q_world_to_cam")
        pos = _numbers(fr["position_m"], "position_m")
        if pos.shape != (3,):
            raise ValueError(f"position_m has shape {pos.shape}, need 3")
        if np.isfinite(pos).all() and float(np.abs(pos).max()) > MAX_POSITION_M:  # before any arithmetic on it
            shown = ", ".join(f"{v:.10g}" for v in pos)  # 10 figures: 1.0000001e7 must not read as the limit
            raise PairFormatError(f"position_m [{shown}] m is over {MAX_POSITION_M:g} m from the origin")
        if "time_s" not in fr:  # frames are ordered by time (DESIGN.md): without one, order cannot be checked
            raise PairFormatError(f"{meta_path}: frame {k}: time_s missing (seconds; frames are ordered by time)")
        pose = Pose(pos, R, float(_number(fr["time_s"], "time_s")))
        img_name = fr["image"]
        if not isinstance(img_name, str) or not img_name:
            raise ValueError("image must be a file name")
        alt = fr.get("altimeter_m")
        alt = math.nan if alt is None else float(_number(alt, "altimeter_m"))
    except PairFormatError as exc:  # the frame's own checks: name the file and the frame once
        text = str(exc)
        raise PairFormatError(text if text.startswith(str(meta_path)) else f"{meta_path}: frame {k}: {text}") from None
    except KeyError as exc:  # a field left out: say what a frame needs
        raise PairFormatError(
            f"{meta_path}: frame {k}: need image, position_m[3], R_world_to_cam[3][3] or q_world_to_cam[4] "
            f"(missing {exc})"
        ) from None
    except (TypeError, ValueError, OverflowError) as exc:  # a field of the wrong kind: that field, by name
        raise PairFormatError(f"{meta_path}: frame {k}: {exc}") from None
    return pose, img_name, alt


def true_poses(pair: Any, where: str | Path = "pair.json") -> tuple[Pose, ...]:
    """Each frame's true pose: ``meta["true_frames"]`` (the renderer keeps there the poses that injected
    navigation errors hide, docs/design.md), else the reported poses. Entries are read as the frames are
    (:func:`_frame_pose`), one per frame; anything else is a :class:`PairFormatError` naming ``where``:
    scoring against the reported pose instead would hide the very error a study injected."""
    tp = pair.meta.get("true_frames") if isinstance(pair.meta, dict) else None
    if tp is None:
        return tuple(pair.poses)
    if not isinstance(tp, list) or len(tp) != len(pair.poses):
        n = len(tp) if isinstance(tp, list) else type(tp).__name__
        raise PairFormatError(f"{where}: true_frames must list one pose per frame ({len(pair.poses)}), got {n}")
    poses = []
    for k, fr in enumerate(tp):
        try:  # the renderer writes each frame's image name here too; a pose needs none
            pose, _, _ = _frame_pose({**fr, "image": "-"} if isinstance(fr, dict) else fr, k, Path(where))
        except PairFormatError as exc:
            text = str(exc).replace(f": frame {k}", f": true_frames[{k}]", 1).replace("need image, ", "need ", 1)
            raise PairFormatError(text) from None
        poses.append(pose.orthonormalised(f"{where}: true_frames[{k}]")[0])
    return tuple(poses)


def _file_kind(mode: int) -> str:
    """What a non-regular file is, in words, from its ``st_mode``."""
    for test, kind in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    ):
        if test(mode):
            return kind
    return "not a file"


MISSING = "missing"


def _not_regular(path: Path) -> str | None:
    """Why ``path`` cannot be read as a regular file (:data:`MISSING`, "cannot be read (why)", "exists but is
    not a regular file (a FIFO)"), or None when it can. Reading a FIFO would block and a directory cannot be
    read: both are named, never taken for a missing file."""
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        return MISSING
    except OSError as exc:  # a name too long, a symlink loop, no permission: say which
        return f"cannot be read ({exc.strerror or exc})"
    return None if stat.S_ISREG(mode) else f"exists but is not a regular file ({_file_kind(mode)})"


def file_present(path: Path) -> bool:
    """Whether an optional file is there: False when nothing has its name, True for a regular file, and
    :class:`PairFormatError` for anything else by that name (:func:`_not_regular`)."""
    why = _not_regular(path)
    if why is not None and why != MISSING:
        raise PairFormatError(f"{path}: {why}")
    return why is None


def _check_regular(path: Path, what: str, d: Path) -> None:
    """Refuse ``path`` (``what`` in pair directory ``d``) unless it is an existing regular file."""
    why = _not_regular(path)
    if why == MISSING:
        # a rendered descent given where one of its pairs is meant read only "missing pair.json" (QA of stop 73)
        descent = what == "pair.json" and (d / "manifest.json").is_file()
        hint = " (it is a rendered descent, manifest.json: give one of its pair directories)" if descent else ""
        raise PairFormatError(f"{d}: missing {what}{hint}")
    if why is not None:
        raise PairFormatError(f"{d}: {what} {why}")


def declared_size(directory: str | Path) -> tuple[int, int, int] | None:
    """(width, height, frames) as a pair directory's pair.json declares them, read without its images, for a memory
    check before they are decoded; None when pair.json cannot be read so (missing, a FIFO, over
    :data:`MAX_PAIR_JSON_BYTES`, not JSON, a width of 1e400): :func:`read_pair` then says what is wrong with it.
    Read whole, a 200 MB pair.json cost its size in memory before it was refused (QA of stop 66)."""
    meta = Path(directory) / "pair.json"
    try:
        if not meta.is_file() or meta.stat().st_size > MAX_PAIR_JSON_BYTES:
            return None
        doc = json.loads(meta.read_text())
        w, h, n = int(doc["camera"]["width"]), int(doc["camera"]["height"]), len(doc["frames"])
    except (OSError, ValueError, TypeError, KeyError, RecursionError, OverflowError):
        return None
    # a size no camera has is the reader's to refuse: a width of 10**30 read as a memory shortfall (QA of stop 85)
    return (w, h, n) if 0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE else None


def named_images(directory: str | Path) -> list[Path]:
    """The images a pair directory's pair.json names, resolved, without reading them: they may lie in
    subdirectories, with any extension (a `score --csv` over `img/frame0.png` replaced a frame). An unreadable
    pair.json names none (a symlink loop is a RuntimeError on 3.11; :func:`read_pair` says what is wrong)."""
    d = Path(directory)
    try:
        if (d / "pair.json").stat().st_size > MAX_PAIR_JSON_BYTES:  # read whole, a huge one cost its size (QA 66b)
            return []
        frames = json.loads((d / "pair.json").read_text(encoding="utf-8"))["frames"]
        return [(d / str(f["image"])).resolve() for f in frames]
    except (OSError, ValueError, KeyError, TypeError, RuntimeError, RecursionError):
        return []


def _image_path(d: Path, name: str) -> Path:
    """The path of image ``name`` named in ``d``'s pair.json: inside ``d``, and a regular file."""
    if "\0" in name:  # no file system can name it; os calls raise ValueError on it
        raise PairFormatError(f"{d / 'pair.json'}: image name {name!r} contains a NUL character")
    shown = name if len(name) <= 80 else f"{name[:60]}... ({len(name)} characters)"  # one readable line
    try:
        p = (d / name).resolve()
    except (RuntimeError, OSError) as exc:  # a symlink loop: RuntimeError up to Python 3.12, OSError after
        raise PairFormatError(f"{d}: image {shown!r} cannot be resolved ({str(exc)[:200]})") from None
    if not p.is_relative_to(d.resolve()):
        link = d / name
        if link.is_symlink() and not link.exists():  # "outside" named the wrong fault
            raise PairFormatError(f"{d}: image {shown!r} is a broken symlink (its target {p} does not exist)")
        via = " (through a symlink)" if p != Path(os.path.normpath((d / name).absolute())) else ""  # not "../"
        raise PairFormatError(f"{d}: image {shown!r} lies outside the pair directory{via}: a pair holds its images")
    _check_regular(p, f"image {shown}", d)
    return p


# what numpy's .npy header parser raises on a damaged header: an unterminated string reaches the tokenizer
# (TokenError), a negative shape the memory map (OverflowError); each was a traceback
NPY_FAULTS = (ValueError, EOFError, OSError, SyntaxError, OverflowError, TypeError, MemoryError, tokenize.TokenError)


def npy_fault(exc: BaseException) -> str:
    """numpy's reason in a reader's words: its advice to unpickle a file is not for a map, and a memory address
    in a parser's message would make the same error differ from run to run."""
    text = re.sub(r" at 0x[0-9a-fA-F]+", "", str(exc))
    if "pickle" in text or "can't be memory-mapped" in text:
        return "not a numeric array: a text file, or Python objects"
    if "mmap length is greater than file size" in text:
        return "truncated: shorter than its header says"
    if isinstance(exc, (SyntaxError, OverflowError, TypeError, tokenize.TokenError)) or "header" in text:
        return f"damaged header ({text[:120]})" if text else "damaged header"
    return text[:200] or "empty file"


def open_npy(path: Path) -> np.ndarray:
    """The array in a ``.npy`` file, memory-mapped: only its header is read, so its shape and dtype can be
    refused before any data is copied; never unpickled (a file from a user can run code). Any fault is one
    :class:`PairFormatError` naming the file."""
    try:
        a = np.load(path, allow_pickle=False, mmap_mode="r")
    except NPY_FAULTS as exc:
        raise PairFormatError(f"{path}: not a readable .npy file ({npy_fault(exc)})") from None
    if not isinstance(a, np.ndarray):  # an .npz archive under a .npy name
        close = getattr(a, "close", None)
        if close is not None:
            close()
        raise PairFormatError(f"{path}: not a single array (.npy) but an .npz archive of several")
    return a


def _load_truth(p: Path, name: str, shape: tuple[int, int]) -> np.ndarray:
    """Ground-truth layer ``name`` from ``p``, refused unless numeric (bool or integer for the shadow mask)
    and of the images' ``shape``; both are read from the header (memory-mapped) before any data is copied."""
    a = open_npy(p)
    kinds, need = ("biu", "bool (or integer 0/1)") if name == "shadow" else ("fiu", "numbers (float32)")
    if a.dtype.kind not in kinds:  # strings, complex, structured, dates: the scores would fail or mean nothing
        raise PairFormatError(f"{p}: ground truth {name} must hold {need}, got dtype {a.dtype}")
    if a.shape != shape:
        raise PairFormatError(f"{p}: ground truth {name}: shape {a.shape} != image shape {shape}")
    if name == "shadow" and a.dtype.kind != "b":
        mask = np.array(a)
        if (bad := (mask != 0) & (mask != 1)).any():  # a 2 (a class code? 255 for true?) passed as shadow, unsaid
            raise PairFormatError(
                f"{p}: ground truth shadow must be bool or integer 0/1; {int(bad.sum())} pixels hold other values, "
                f"e.g. {mask[bad].flat[0]}"
            )
        return mask != 0
    out = np.array(a)
    if name in ("depth", "elevation"):  # NaN where unknown; an inf was taken as ground, a negative depth as a
        # scene with no common ground (QA of stop 66)
        bad = np.isinf(out) | ((out <= 0) if name == "depth" else np.zeros(out.shape, bool))
        if bad.any():
            what = "a finite z-depth > 0 (in front of the camera)" if name == "depth" else "a finite Z"
            raise PairFormatError(
                f"{p}: ground truth {name} must be {what}, or NaN where unknown; {int(bad.sum())} pixels hold "
                f"other values, e.g. {out[bad].flat[0]:g}"
            )
    if name == "hazard":  # a 5.0 (a slope in degrees?) was read as merely unsafe, without a word
        bad = ~np.isnan(out) & ~((out >= 0) & (out <= 1))
        if bad.any():
            raise PairFormatError(
                f"{p}: ground truth hazard must lie in [0, 1] (1 = unsafe) or be NaN where unknown; "
                f"{int(bad.sum())} pixels hold other values, e.g. {out[bad].flat[0]:g}"
            )
    return out


def read_pair(directory: str | Path, *, load_truth: bool = True) -> Pair:
    """Read and validate a pair directory; every problem raises :class:`PairFormatError`, a file the system
    will not let us read too (it was an OSError: exit 1 where every other bad pair is exit 2). Without
    ``load_truth`` neither the truth files nor pair.json's truth (:data:`TRUTH_META_KEYS`) are read."""
    try:
        return _read_pair(directory, load_truth=load_truth)
    except OSError as exc:
        raise PairFormatError(os_error_text(exc, "read")) from None


def _read_pair(directory: str | Path, *, load_truth: bool) -> Pair:
    import cv2

    d = Path(directory)
    if not d.is_dir():
        raise PairFormatError(f"{d}: not a directory")
    meta_path = d / "pair.json"
    _check_regular(meta_path, "pair.json", d)
    doc = _load_json(meta_path)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise PairFormatError(f"{meta_path}: format must be {FORMAT!r}, got {got!r:.60}")
    try:
        camera = Camera.from_dict(doc.get("camera") or {})
    except PairFormatError as exc:  # the camera's checks speak of its fields; name the file they are in
        raise PairFormatError(f"{meta_path}: {exc}") from None
    frames = doc.get("frames")
    if not isinstance(frames, list) or not MIN_FRAMES <= len(frames) <= MAX_FRAMES:
        kinds = {dict: "an object", str: "a string", bool: "true or false", int: "a number", float: "a number"}
        n = len(frames) if isinstance(frames, list) else "none" if frames is None else kinds.get(type(frames), "?")
        raise PairFormatError(f"{meta_path}: 'frames' must list {MIN_FRAMES} to {MAX_FRAMES} frames, got {n}")
    notes: list[str] = []
    poses, raw, names, paths, alts = [], [], [], [], []
    for k, fr in enumerate(frames):
        pose, img_name, alt = _frame_pose(fr, k, meta_path)
        pose, note = pose.orthonormalised(f"{meta_path}: frame {k}")
        if note:
            notes.append(note)
        img_path = _image_path(d, img_name)
        w, h = image_header_size(img_path)
        if (w, h) != (camera.width, camera.height):
            raise PairFormatError(
                f"{img_path}: size {w}x{h} does not match the camera's {camera.width}x{camera.height}"
            )
        data = img_path.read_bytes()  # read once: checked (a PNG), then decoded from these bytes
        damage = png_damage(data)
        if damage:
            raise PairFormatError(f"{img_path}: not a readable image ({damage})")
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        del data
        if img is None:
            raise PairFormatError(f"{img_path}: not a readable image")
        poses.append(pose)
        raw.append(img)
        names.append(img_name)
        paths.append(img_path)
        alts.append(alt)
    images, conv, shallow = to_gray8(raw, names, paths)
    notes += conv
    sun = None
    if doc.get("sun") is not None:
        if not isinstance(doc["sun"], dict):  # Python's "string indices must be integers" said nothing of the format
            raise PairFormatError(
                f'{meta_path}: sun must be an object {{"azimuth_deg": ..., "elevation_deg": ...}}, got '
                f"{json.dumps(doc['sun'])[:60]}"
            )
        try:
            # JSON numbers, as every other field: "135" passed through float() unnoticed (QA of stop 66)
            sun = Sun(
                float(_number(doc["sun"]["azimuth_deg"], "sun.azimuth_deg")),
                float(_number(doc["sun"]["elevation_deg"], "sun.elevation_deg")),
            )
        except KeyError as exc:
            raise PairFormatError(f"{meta_path}: sun needs azimuth_deg and elevation_deg (missing {exc})") from None
        except (TypeError, ValueError, OverflowError) as exc:
            raise PairFormatError(f"{meta_path}: sun needs azimuth_deg and elevation_deg ({exc})") from None
        # a NaN angle would make the flight software drop the sun without a word (a different result)
        if not (math.isfinite(sun.azimuth_deg) and math.isfinite(sun.elevation_deg)):
            raise PairFormatError(
                f"{meta_path}: sun angles must be finite, got azimuth_deg {sun.azimuth_deg}, "
                f"elevation_deg {sun.elevation_deg}"
            )
        # the flight software's own limits, said here with the file's field names
        if not abs(sun.azimuth_deg) <= SUN_AZIMUTH_LIMIT_DEG:
            lim = SUN_AZIMUTH_LIMIT_DEG
            raise PairFormatError(
                f"{meta_path}: sun.azimuth_deg must be in [{-lim:g}, {lim:g}], got {sun.azimuth_deg:g}"
            )
        if not 0.0 < sun.elevation_deg <= 90.0:
            raise PairFormatError(f"{meta_path}: sun.elevation_deg must be in (0, 90], got {sun.elevation_deg:g}")
    truth: dict[str, np.ndarray] = {}
    if load_truth:
        for name, fname in TRUTH_FILES.items():
            p = d / fname
            if os.path.lexists(p):  # optional; but one that is there must be a readable array
                _check_regular(p, fname, d)
                truth[name] = _load_truth(p, name, (camera.height, camera.width))
    left_out = ("format", "camera", "frames", "sun", *(() if load_truth else TRUTH_META_KEYS))
    meta = {k: v for k, v in doc.items() if k not in left_out}
    pair = Pair(camera, tuple(poses), tuple(images), sun, truth, meta, tuple(alts), notes)
    if load_truth:
        true_poses(pair, meta_path)  # a study's truth that cannot be read is refused here, not met mid-score
    try:
        pair.validate()
    except PairFormatError as exc:  # validate() speaks of frames; name the file they are in
        raise PairFormatError(f"{meta_path}: {exc}") from None
    # implausible scales make the maps meaningless: warnings, which `process` records with its outputs (they were
    # notes on stderr alone: a pair in km gave a DEM in km with an empty result.json warnings; QA of stop 75)
    pair.warnings += [f"{meta_path}: {n}" for n in pair.scale_notes()]
    pair.warnings += list(shallow.values())
    pair.shallow_warnings = dict(shallow)
    pair.notes += [f"{meta_path}: {n}" for n in same_time_notes(pair.poses)]
    pair.warnings += unknown_keys(doc.get("camera"), CAMERA_KEYS, f"{meta_path}: camera")
    pair.warnings += [w for k, fr in enumerate(frames) for w in unknown_keys(fr, FRAME_KEYS, f"{meta_path}: frame {k}")]
    pair.warnings += unknown_keys(doc.get("sun"), SUN_KEYS, f"{meta_path}: sun")
    return pair


def same_time_notes(poses: Sequence[Pose]) -> list[str]:
    """Consecutive frames at one ``time_s`` but different heights: allowed (time must not run backwards), but no
    lander drops 50 m in no time, so the times are likely wrong (a tool that wrote 0 for each; QA 74)."""
    out = []
    for k in range(1, len(poses)):
        t0, t1 = poses[k - 1].time_s, poses[k].time_s
        if t1 == t0:
            dz = float(poses[k - 1].position[2] - poses[k].position[2])
            out.append(
                f"frames {k - 1} and {k} have the same time_s ({t1:g} s) {dz:g} m apart in height: frames are "
                "ordered by time, so check the times"
            )
    return out


MANIFEST_FORMAT = "hazard-hil-descent/1"


def read_manifest(path: str | Path) -> dict[str, Any]:
    """A descent's ``manifest.json`` (docs/design.md, "Streaming your own pairs"), checked: a JSON object whose
    ``format``, if given, is :data:`MANIFEST_FORMAT`, with a non-empty list ``pairs`` of objects, each with a
    string ``path`` (the pair directory, relative to the manifest), an optional string ``label`` and an optional
    numeric ``altitude_m``. One-line :class:`PairFormatError` otherwise. The pair directories themselves are
    read when their turn comes: a bad pair is that pair's error, and the descent goes on."""
    manifest = Path(path)
    try:
        if manifest.stat().st_size > MAX_MANIFEST_BYTES:  # read whole below: its size in memory before a word
            raise PairFormatError(
                f"manifest {manifest}: {manifest.stat().st_size} bytes is more than a manifest can be "
                f"({MAX_MANIFEST_BYTES} bytes)"
            )
        doc = json.loads(manifest.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise PairFormatError(f"manifest {manifest}: cannot be read ({exc})") from None
    except ValueError as exc:
        raise PairFormatError(f"manifest {manifest}: not JSON ({exc})") from None
    except RecursionError:  # json's parser recurses once per nested list or object
        raise PairFormatError(f"manifest {manifest}: JSON nested too deeply") from None
    if not isinstance(doc, dict):
        raise PairFormatError(f'manifest {manifest}: must be a JSON object with "pairs", got {type(doc).__name__}')
    if doc.get("format", MANIFEST_FORMAT) != MANIFEST_FORMAT:
        raise PairFormatError(f"manifest {manifest}: format must be {MANIFEST_FORMAT!r}, got {doc['format']!r}")
    pairs = doc.get("pairs")
    if not isinstance(pairs, list) or not pairs:
        raise PairFormatError(f'manifest {manifest}: "pairs" must be a non-empty list of pair entries')
    for i, e in enumerate(pairs):
        where = f"manifest {manifest}: pair {i}"
        if not isinstance(e, dict):
            raise PairFormatError(f'{where} must be an object with a "path", got {json.dumps(e)[:40]}')
        if not isinstance(e.get("path"), str) or not e["path"]:
            raise PairFormatError(f'{where} has no "path" (the pair directory, relative to the manifest)')
        if "label" in e and not isinstance(e["label"], (str, int)):
            raise PairFormatError(f'{where}: "label" must be a string, got {json.dumps(e["label"])[:40]}')
        alt = e.get("altitude_m")
        if alt is not None and (isinstance(alt, bool) or not isinstance(alt, (int, float)) or not math.isfinite(alt)):
            raise PairFormatError(f'{where}: "altitude_m" must be a number of metres, got {json.dumps(alt)[:40]}')
    return doc


def square_camera(size: int, option: str = "--image-size") -> Camera:
    """:meth:`Camera.thesis` at ``size`` px, after one check of the size every command that makes one shares."""
    if isinstance(size, bool) or not isinstance(size, int) or not IMAGE_SIZE_MIN <= size <= IMAGE_SIZE_MAX:
        raise InputError(f"{option} must be {IMAGE_SIZE_MIN}..{IMAGE_SIZE_MAX} px, got {size}")
    return Camera.thesis(size)
