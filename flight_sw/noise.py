"""Image noise: a frame whose pixels are far noisier than the others' (a sensor fault, a damaged image).

Nothing in the flight software looked at image quality: a descent frame with Gaussian noise of 30 grey levels
was refined, swept and mapped like any other, its DEM 3-5x worse, with sites and no word (stop 61's QA). The
pose refinement tracks high-passed corners and the sweep's correlation is normalised, so both take a noisy
image in their stride; only its noise level tells it apart.

The estimate is Immerkaer's (1996, "Fast noise variance estimation", CVIU 64(2)): the image convolved with

    N = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]

(the difference of two Laplacians, which cancels every linear ramp and most of a smooth image) responds to
white noise of sd ``s`` with sd ``6 s`` (the kernel's squares sum to 36). Immerkaer averages ``|I * N|``; the
median is taken here instead, ``s = median|I * N| / (0.6745 * 6)``, so that the terrain's edges and texture,
which are sparse, weigh less than the noise, which is everywhere.

Clean renders still read texture as noise: 1.0-15.8 grey levels over the scenes of the library (a bright
highland the most), and frames of one descent differ by up to 2.9x (tuning renders, stop 61). A frame more
than :data:`NOISY_RATIO` times the median of the others' is called noisy; one under :data:`MIN_REFERENCE` and
under ``1 / NOISY_RATIO`` of theirs is called blank (a uniform image reads 0: a black, saturated or lost frame).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_MAD_TO_SD = 0.6745  # median |x| of a zero-mean Gaussian, in sds
# clean descents (tuning renders of the six library scenes, 256 and 512 px, stop 61): at most 2.9x between
# frames; a frame with Gaussian noise of 30 grey levels reads 5.9x or more over the others'
NOISY_RATIO = 4.0
# the quietest clean frames read 1.0-1.2 (a polar low sun, a mare); a uniform image reads 0
MIN_REFERENCE = 0.75
# ... and a frame under this reads as uniform even with no other frame to compare (a lost or black frame)
UNIFORM_DN = 0.05


def noise_sigma(image: np.ndarray, step: int = 2) -> float:
    """The image's white-noise sd in grey levels, ``median|I * N| / (0.6745 * 6)`` (module doc), read on every
    ``step``-th row and column of the response (the median needs no more). A float image in [0, 1] is taken as
    0..255, as the pose refinement takes it (:data:`MIN_REFERENCE` is in 8-bit levels). NaN for an image under
    3x3."""
    a = np.asarray(image, np.float32)
    if a.ndim != 2 or min(a.shape) < 3:
        return float("nan")
    if np.issubdtype(np.asarray(image).dtype, np.floating) and float(a.max()) <= 1.0:
        a = a * 255.0
    r = cv2.filter2D(a, -1, _KERNEL, borderType=cv2.BORDER_REFLECT)[1:-1:step, 1:-1:step]
    return float(np.median(np.abs(r))) / (_MAD_TO_SD * 6.0)


def noisy_frames(sigmas: Sequence[float], ratio: float = NOISY_RATIO) -> list[int]:
    """The frames whose noise sd is more than ``ratio`` times the median of the other frames' (two frames: the
    other's). A frame under :data:`MIN_REFERENCE` grey levels (a blank image, a black one) is no reference: its
    partner would read as noisy."""
    s = [float(v) for v in sigmas]
    out = []
    for k, v in enumerate(s):
        others = [o for j, o in enumerate(s) if j != k and np.isfinite(o) and o >= MIN_REFERENCE]
        if others and np.isfinite(v) and v > ratio * float(np.median(others)):
            out.append(k)
    return out


def blank_frames(sigmas: Sequence[float], ratio: float = NOISY_RATIO) -> list[int]:
    """The frames with next to no pixel-scale detail: under :data:`MIN_REFERENCE` grey levels and under
    ``1 / ratio`` of the median of the other frames' that read at least that (a black, saturated or lost image
    reads 0; the quietest clean frames 1.0-1.2). Frame 0 blank left every other frame "could not check", the
    maps empty, and nothing named it (stop 62)."""
    s = [float(v) for v in sigmas]
    out = []
    for k, v in enumerate(s):
        others = [o for j, o in enumerate(s) if j != k and np.isfinite(o) and o >= MIN_REFERENCE]
        if not np.isfinite(v) or v >= MIN_REFERENCE:
            continue
        # with no frame to judge against, only a frame with next to no detail at all (a uniform image reads 0):
        # an all-black pair named no frame (stop 62's review)
        if (v * ratio < float(np.median(others))) if others else v < UNIFORM_DN:
            out.append(k)
    return out
