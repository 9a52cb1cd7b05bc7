"""Argument checks for the flight-software library entry points.

Every problem raises :class:`FlightInputError` (an :class:`protocol.errors.InputError`)
with a message naming the argument, so callers never see a bare numpy traceback.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from protocol.errors import InputError
from protocol.pairdir import MAX_POSITION_M, Camera, PairFormatError, Pose, check_sees_ground


class FlightInputError(InputError):
    """Bad arrays, poses or parameters passed to the flight-software pipeline."""


def check_image(img: np.ndarray, name: str, camera: Camera) -> np.ndarray:
    """Return ``img`` as a 2-D array of the camera's size; reject NaN and wrong shapes."""
    if not isinstance(img, np.ndarray):
        raise FlightInputError(f"{name}: expected a numpy array, got {type(img).__name__}")
    if img.ndim != 2:
        raise FlightInputError(f"{name}: must be a 2-D gray image, got shape {img.shape}")
    if img.shape != (camera.height, camera.width):
        raise FlightInputError(
            f"{name}: size {img.shape[1]}x{img.shape[0]} does not match the camera's {camera.width}x{camera.height}"
        )
    if not np.issubdtype(img.dtype, np.number) or np.issubdtype(img.dtype, np.complexfloating):
        raise FlightInputError(f"{name}: must be real-valued, got dtype {img.dtype}")
    if np.issubdtype(img.dtype, np.floating) and not np.all(np.isfinite(img)):
        raise FlightInputError(f"{name}: contains NaN or inf")
    if img.dtype != np.uint8 and img.size:
        # the costs, texture floors and shadow levels are in 8-bit grey levels (DESIGN.md's images): a [0, 1] float
        # image gave an empty DEM reported as level "full", a 16-bit one 9 % of it (review of stop 64)
        lo, hi = float(img.min()), float(img.max())
        if lo < 0 or hi > 255:
            raise FlightInputError(
                f"{name}: grey levels must lie in 0-255 (8-bit, DESIGN.md), got {lo:g}-{hi:g} ({img.dtype}); "
                "scale the image to 0-255"
            )
        if np.issubdtype(img.dtype, np.floating) and 0 < hi <= 1.0:
            raise FlightInputError(
                f"{name}: a {img.dtype} image in 0-{hi:g} reads as 0-1 intensities (or is all but black); grey "
                "levels are 0-255 (8-bit, DESIGN.md): multiply by 255"
            )
    return img


def check_geometry(camera: Camera, poses: list[Pose]) -> None:
    """Finite is not enough: values far outside any descent make the geometry overflow (a pose at 1e308 m
    gave NaN parallax deep in the sweep). Bounds: the camera's of the pair format (:meth:`Camera.validate`:
    focal lengths up to ``MAX_FOCAL_SIDES`` image sides, the principal point within ``MAX_PRINCIPAL_SIDES``
    sides of the image), ``|position| <= MAX_POSITION_M``."""
    try:
        camera.validate()  # one statement of the camera's bounds, the reader's, for callers of the API too
    except PairFormatError as exc:
        raise FlightInputError(str(exc)) from None
    for k, pose in enumerate(poses):
        if float(np.abs(pose.position).max()) > MAX_POSITION_M:
            raise FlightInputError(
                f"pose{k + 1}: position [{', '.join(f'{float(v):.4g}' for v in pose.position)}] m is over "
                f"{MAX_POSITION_M:g} m from "
                "the origin"
            )
        # the reader's rule, for the frames of a link too: a camera looking up failed in OpenCV's remap as a
        # pipeline_failure, one looking at the horizon in numpy's divide warnings (QA of stop 85)
        try:
            check_sees_ground(pose, f"pose{k + 1}")
        except PairFormatError as exc:
            raise FlightInputError(str(exc)) from None


MIN_IMAGE_SIDE = 8  # the smallest camera the pipeline maps (an 8 px camera runs; 1 and 2 px ones crashed)


def check_inputs(i1: np.ndarray, i2: np.ndarray, pose1: Pose, pose2: Pose, camera: Camera) -> None:
    """Validate the pipeline's inputs: camera, images, poses, and i2 taken below i1."""
    if not isinstance(camera, Camera):
        raise FlightInputError(f"camera: expected protocol.pairdir.Camera, got {type(camera).__name__}")
    for name, pose in (("pose1", pose1), ("pose2", pose2)):
        if not isinstance(pose, Pose):
            raise FlightInputError(f"{name}: expected protocol.pairdir.Pose, got {type(pose).__name__}")
    try:
        camera.validate()
        pose1.validate("pose1")
        pose2.validate("pose2")
    except PairFormatError as exc:
        raise FlightInputError(str(exc)) from None
    if min(camera.width, camera.height) < MIN_IMAGE_SIDE:  # 1 and 2 px cameras crashed the sweep (QA 66b)
        raise FlightInputError(
            f"camera: images of {camera.width}x{camera.height} px are too small to map: the pipeline needs at least "
            f"{MIN_IMAGE_SIDE} px a side"
        )
    check_geometry(camera, [pose1, pose2])
    check_image(i1, "i1", camera)
    check_image(i2, "i2", camera)
    if not pose2.position[2] < pose1.position[2]:
        raise FlightInputError(
            f"pose2 must be below pose1 (z = {pose2.position[2]:.3f} m vs {pose1.position[2]:.3f} m): "
            "i1 is the higher image"
        )
    if pose1.position[2] <= 0 or pose2.position[2] <= 0:
        raise FlightInputError("poses must be above the reference plane Z = 0 (positive altitude)")


def check_frames(images: list[np.ndarray], poses: list[Pose], camera: Camera, max_frames: int = 16) -> None:
    """Validate 2-``max_frames`` frames ordered by time (``i1`` highest): :func:`check_inputs` on the
    first two, then each further image and pose, each frame below the one before."""
    if not isinstance(images, (list, tuple)) or not isinstance(poses, (list, tuple)):
        raise FlightInputError("images and poses must be lists (one entry per frame)")
    if not 2 <= len(images) <= max_frames or len(poses) != len(images):
        raise FlightInputError(
            f"need 2-{max_frames} frames with one pose each, got {len(images)} images and {len(poses)} poses"
        )
    check_inputs(images[0], images[1], poses[0], poses[1], camera)
    for k in range(2, len(images)):
        pose = poses[k]
        if not isinstance(pose, Pose):
            raise FlightInputError(f"pose{k + 1}: expected protocol.pairdir.Pose, got {type(pose).__name__}")
        try:
            pose.validate(f"pose{k + 1}")
        except PairFormatError as exc:
            raise FlightInputError(str(exc)) from None
        check_geometry(camera, [pose])
        check_image(images[k], f"i{k + 1}", camera)
        if not pose.position[2] < poses[k - 1].position[2]:
            raise FlightInputError(
                f"pose{k + 1} must be below pose{k} (z = {pose.position[2]:.3f} m vs "
                f"{poses[k - 1].position[2]:.3f} m): frames are ordered by time, i1 the highest"
            )


# The pipeline's peak memory per camera pixel over a process's base (bench/bench_flight_memory.py, stop 35: an
# oblique approach pair, the largest, 169-171 B at 512^2 and 1024^2), plus what each frame costs as read and as
# float32, and the base of a process that has imported numpy and OpenCV (~34 MiB). The HIL keeps its own model of
# the whole flight process, measured from outside (hil_server.budgets.flight_peak_rss_mib: fusion and the link too),
# because a user's flight program can take our pipeline's place there
PIPELINE_BYTES_PER_PIXEL = 180
FRAME_BYTES_PER_PIXEL = 5
PROCESS_BASE_BYTES = 34 * 2**20


# `process` draws its pictures after the pipeline: matplotlib, its canvases and the RGBA copies. Peak RSS of
# `process` at 512, 1024, 2048 and 4096 px: 255 MiB, 510 MiB, 1.34 GiB and 4.7 GiB against the pipeline's 82, 224,
# 830 and 3140 MiB (QA of stop 71); a camera that passed the check ended in a traceback while drawing
PICTURES_BASE_BYTES = 180 * 2**20
PICTURES_BYTES_PER_PIXEL = 110


def peak_memory_bytes(width: int, height: int, n_frames: int, pictures: bool = False) -> int:
    """Expected peak memory (bytes) of running the pipeline on ``n_frames`` frames of ``width x height``:
    ``base + (PIPELINE_BYTES_PER_PIXEL + FRAME_BYTES_PER_PIXEL n_frames) width height``, plus
    ``PICTURES_BASE_BYTES + PICTURES_BYTES_PER_PIXEL width height`` when ``pictures`` are drawn after it. Extra
    frames add no more than their own images: the cost volume they join is combined plane by plane (measured on
    a 4-frame descent: 2, 3 and 4 frames peak alike)."""
    px = max(0, int(width)) * max(0, int(height))
    need = PROCESS_BASE_BYTES + (PIPELINE_BYTES_PER_PIXEL + FRAME_BYTES_PER_PIXEL * max(0, int(n_frames))) * px
    return need + (PICTURES_BASE_BYTES + PICTURES_BYTES_PER_PIXEL * px if pictures else 0)


ADDRESS_SPACE_SLACK_BYTES = 256 * 2**20  # mapped, not resident: OpenCV's thread stacks, glibc arenas


def memory_room() -> tuple[int, str]:
    """The bytes this process can still spend, and what bounds them: the least of the host's free memory
    (``psutil.virtual_memory().available``), the address space left under ``RLIMIT_AS`` (``ulimit -v``,
    ``prlimit --as``: its current mappings already count) and the room left under its cgroup v2
    ``memory.max`` (a container's limit)."""
    import resource

    import psutil

    room = (int(psutil.virtual_memory().available), "of memory is available")
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        # the process's base is mapped already (counted in vms and in the need alike: added back), and the work
        # maps more than it touches (thread stacks, allocator arenas): a necessary bound, not a sufficient one
        left = int(soft) - int(psutil.Process().memory_info().vms) + PROCESS_BASE_BYTES - ADDRESS_SPACE_SLACK_BYTES
        if left < room[0]:
            room = (max(0, left), "of address space is left under this process's limit (ulimit -v)")
    group = _cgroup_room()
    if group is not None and group < room[0]:
        room = (group, "is left under this process's cgroup memory limit (memory.max)")
    return room


def _cgroup_room() -> int | None:
    """``memory.max - memory.current`` of this process's cgroup v2, None where there is no such limit."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
        rel = next(line[3:] for line in lines if line.startswith("0::"))
        base = Path("/sys/fs/cgroup") / rel.lstrip("/")
        limit = (base / "memory.max").read_text().strip()
        if limit == "max":
            return None
        # memory.current counts page cache the kernel would reclaim first: the working set is current minus
        # inactive_file (as container runtimes count it), else a container that just read its renders refused
        stat = dict(line.split() for line in (base / "memory.stat").read_text().splitlines() if " " in line)
        used = int((base / "memory.current").read_text()) - int(stat.get("inactive_file", 0))
        return max(0, int(limit) - max(0, used))
    except (OSError, StopIteration, ValueError):
        return None


def check_memory(
    width: int, height: int, n_frames: int, available_bytes: int | None = None, pictures: bool = False
) -> None:
    """Refuse, before anything is read, work whose :func:`peak_memory_bytes` exceeds the memory this process can
    spend (:func:`memory_room` unless given): the operating system, or the allocator under a limit, would end it
    part-way."""
    need = peak_memory_bytes(width, height, n_frames, pictures)
    what = "of memory is available"
    if available_bytes is None:
        available_bytes, what = memory_room()
    if need > available_bytes:
        raise FlightInputError(
            f"{width}x{height} px x {n_frames} frames needs ~{need / 2**20:.0f} MiB to process, but only "
            f"{available_bytes / 2**20:.0f} MiB {what} (use a smaller camera or fewer frames)"
        )
