"""The pair directory: two descent images, their poses and optional ground truth.

This is the offline exchange format between ``ground_sim`` (writer) and
``flight_sw`` (reader), and the way users bring their own images. The layout
is fixed by ``shared/DESIGN.md``::

    pair.json              {"format": "sfm-hd-pair/1", "camera": {...},
                            "frames": [{"image", "position_m", "R_world_to_cam", "time_s"}, x2],
                            "sun": {"azimuth_deg", "elevation_deg"}}   # sun optional
    i1.png, i2.png         8-bit gray; frame 0 is the higher (earlier) image
    gt_elevation_i1.npy    optional float32 HxW, world Z seen by each pixel of i1
    gt_depth_i1.npy        optional float32 HxW, camera-1 z-depth
    gt_shadow_i1.npy       optional bool HxW, pixel of i1 not directly lit
    gt_hazard_i1.npy       optional float32 HxW in [0,1], ground-truth hazard (DESIGN.md rules)

Conventions: world Z up; camera frame is OpenCV's (x right, y down, z forward);
a pose is the centre ``C`` (world) and ``R`` (world->camera), so
``X_cam = R (X_world - C)``. Extra top-level keys in ``pair.json`` (for example
the true poses behind injected pose errors) are kept in :attr:`Pair.meta`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from protocol.errors import InputError

FORMAT = "sfm-hd-pair/1"
TRUTH_FILES = {
    "elevation": "gt_elevation_i1.npy",
    "depth": "gt_depth_i1.npy",
    "shadow": "gt_shadow_i1.npy",
    "hazard": "gt_hazard_i1.npy",
}
_TRUTH_DTYPES = {"elevation": np.float32, "depth": np.float32, "shadow": np.bool_, "hazard": np.float32}


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
    def thesis(cls) -> Camera:
        """The thesis camera (Table 2.2, eq. 3.16): 512x512, 30 deg FOV."""
        f = 256.0 / math.tan(math.radians(15.0))  # 955.405 px
        return cls(512, 512, f, f, 255.5, 255.5)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict[str, float | int]:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        try:
            cam = cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise PairFormatError(f"camera: need width, height, fx, fy, cx, cy ({exc})") from None
        cam.validate()
        return cam

    def validate(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if self.width <= 0 or self.height <= 0:
            raise PairFormatError(f"camera: size must be positive, got {self.width}x{self.height}")
        if not all(math.isfinite(v) for v in vals) or self.fx <= 0 or self.fy <= 0:
            raise PairFormatError(f"camera: focal lengths must be finite and positive, got {vals}")


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
        err = float(np.abs(self.R @ self.R.T - np.eye(3)).max())
        if err > tol:
            raise PairFormatError(f"{what}: R_world_to_cam is not orthonormal (max |R R^T - I| = {err:.2e})")
        if np.linalg.det(self.R) < 0:
            raise PairFormatError(f"{what}: R_world_to_cam is a reflection (det < 0)")

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


@dataclass
class Pair:
    """Two descent frames: index 0 is the higher, earlier image ``i1``."""

    camera: Camera
    poses: tuple[Pose, Pose]
    images: tuple[np.ndarray, np.ndarray]
    sun: Sun | None = None
    truth: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        """Check sizes, dtypes, poses and the altitude order; raise :class:`PairFormatError`."""
        self.camera.validate()
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
        if not self.poses[1].position[2] < self.poses[0].position[2]:
            raise PairFormatError(
                f"frame 1 must be below frame 0 (z = {self.poses[1].position[2]:.3f} m vs "
                f"{self.poses[0].position[2]:.3f} m): frame 0 is the higher image"
            )
        for name, arr in self.truth.items():
            if name not in TRUTH_FILES:
                raise PairFormatError(f"unknown ground-truth layer {name!r}")
            if arr.shape != shape:
                raise PairFormatError(f"ground truth {name}: shape {arr.shape} != image shape {shape}")


def write_pair(directory: str | Path, pair: Pair) -> Path:
    """Write ``pair`` in the DESIGN.md layout; returns the directory."""
    import cv2

    pair.validate()
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    names = ("i1.png", "i2.png")
    for name, img in zip(names, pair.images):
        if not cv2.imwrite(str(d / name), img):
            raise OSError(f"could not write {d / name}")
    doc: dict[str, Any] = {
        "format": FORMAT,
        "camera": pair.camera.to_dict(),
        "frames": [p.to_dict(n) for p, n in zip(pair.poses, names)],
    }
    if pair.sun is not None:
        doc["sun"] = {"azimuth_deg": pair.sun.azimuth_deg, "elevation_deg": pair.sun.elevation_deg}
    for key, value in pair.meta.items():
        if key in doc:
            raise PairFormatError(f"meta key {key!r} collides with a format key")
        doc[key] = value
    (d / "pair.json").write_text(json.dumps(doc, indent=1, sort_keys=False) + "\n")
    for name, arr in pair.truth.items():
        np.save(d / TRUTH_FILES[name], np.asarray(arr, dtype=_TRUTH_DTYPES[name]))
    return d


def read_pair(directory: str | Path, *, load_truth: bool = True) -> Pair:
    """Read and validate a pair directory; every problem raises :class:`PairFormatError`."""
    import cv2

    d = Path(directory)
    if not d.is_dir():
        raise PairFormatError(f"{d}: not a directory")
    meta_path = d / "pair.json"
    if not meta_path.is_file():
        raise PairFormatError(f"{d}: missing pair.json")
    try:
        doc = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PairFormatError(f"{meta_path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise PairFormatError(
            f"{meta_path}: format must be {FORMAT!r}, got {doc.get('format') if isinstance(doc, dict) else doc!r}"
        )
    camera = Camera.from_dict(doc.get("camera") or {})
    frames = doc.get("frames")
    if not isinstance(frames, list) or len(frames) != 2:
        raise PairFormatError(f"{meta_path}: 'frames' must list exactly two frames")
    poses, images = [], []
    for k, fr in enumerate(frames):
        try:
            pose = Pose(
                np.array(fr["position_m"], dtype=float),
                np.array(fr["R_world_to_cam"], dtype=float),
                float(fr.get("time_s", 0.0)),
            )
            img_name = str(fr["image"])
        except (KeyError, TypeError, ValueError) as exc:
            raise PairFormatError(
                f"{meta_path}: frame {k}: need image, position_m[3], R_world_to_cam[3][3] ({exc})"
            ) from None
        img_path = d / img_name
        if not img_path.is_file():
            raise PairFormatError(f"{d}: missing image {img_name}")
        img = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise PairFormatError(f"{img_path}: not a readable image")
        if img.ndim == 3:
            raise PairFormatError(f"{img_path}: must be 8-bit gray, got {img.shape[2]} channels")
        if img.dtype != np.uint8:
            raise PairFormatError(f"{img_path}: must be 8-bit, got {img.dtype}")
        poses.append(pose)
        images.append(img)
    sun = None
    if doc.get("sun") is not None:
        try:
            sun = Sun(float(doc["sun"]["azimuth_deg"]), float(doc["sun"]["elevation_deg"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise PairFormatError(f"{meta_path}: sun needs azimuth_deg and elevation_deg ({exc})") from None
    truth: dict[str, np.ndarray] = {}
    if load_truth:
        for name, fname in TRUTH_FILES.items():
            p = d / fname
            if p.is_file():
                try:
                    truth[name] = np.load(p, allow_pickle=False)
                except ValueError as exc:
                    raise PairFormatError(f"{p}: unreadable ({exc})") from None
    meta = {k: v for k, v in doc.items() if k not in ("format", "camera", "frames", "sun")}
    pair = Pair(camera, (poses[0], poses[1]), (images[0], images[1]), sun, truth, meta)
    pair.validate()
    return pair
