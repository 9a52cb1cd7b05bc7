"""Argument checks for the flight-software library entry points.

Every problem raises :class:`FlightInputError` (an :class:`protocol.errors.InputError`)
with a message naming the argument, so callers never see a bare numpy traceback.
"""

from __future__ import annotations

import numpy as np

from protocol.errors import InputError
from protocol.pairdir import Camera, PairFormatError, Pose


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
    return img


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
        check_image(images[k], f"i{k + 1}", camera)
        if not pose.position[2] < poses[k - 1].position[2]:
            raise FlightInputError(
                f"pose{k + 1} must be below pose{k} (z = {pose.position[2]:.3f} m vs "
                f"{poses[k - 1].position[2]:.3f} m): frames are ordered by time, i1 the highest"
            )
