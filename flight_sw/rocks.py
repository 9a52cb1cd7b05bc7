"""Rock detection (thesis sec 4.2, eq. 4.4-4.8): Harris corner response on i1, thresholded and dilated.

``M = [[Ix^2, IxIy], [IxIy, Iy^2]]`` summed over a Gaussian window, derivatives
from the 3x3 Prewitt-like kernels of eq. 4.6/4.7; response
``R = det(M) - alpha tr(M)^2`` (eq. 4.5 prints ``tr(M)`` unsquared - a typo
against Harris & Stephens, which the thesis's own appendix C squares);
rock pixels are ``R > k mean(R)`` with ``k = 11`` (eq. 4.8), dilated to take
in the rock's immediate surroundings (shadow and rim pixels).
"""

from __future__ import annotations

import cv2
import numpy as np

_DX = np.array([[-1.0, 0.0, 1.0]] * 3, dtype=np.float32)


def harris_response(img: np.ndarray, alpha: float = 0.04, sigma: float = 1.0) -> np.ndarray:
    """Harris corner response ``det(M) - alpha tr(M)^2`` (float32, same shape as ``img``)."""
    I = img.astype(np.float32)
    ix = cv2.filter2D(I, -1, _DX, borderType=cv2.BORDER_REFLECT)
    iy = cv2.filter2D(I, -1, _DX.T.copy(), borderType=cv2.BORDER_REFLECT)
    sxx = cv2.GaussianBlur(ix * ix, (0, 0), sigma)
    syy = cv2.GaussianBlur(iy * iy, (0, 0), sigma)
    sxy = cv2.GaussianBlur(ix * iy, (0, 0), sigma)
    tr = sxx + syy
    return sxx * syy - sxy * sxy - alpha * tr * tr


def rock_mask(
    img: np.ndarray, k: float = 11.0, alpha: float = 0.04, dilate_px: int = 2, sigma: float = 1.0
) -> np.ndarray:
    """Boolean rock map: Harris response above ``k * mean(response)``, dilated by ``dilate_px``.

    If the mean response is not positive (an image of pure edges), the mean of
    ``|R|`` is used so a threshold still exists.
    """
    R = harris_response(img, alpha, sigma)
    mu = float(R.mean())
    if mu <= 0:
        mu = float(np.abs(R).mean())
    if mu == 0:
        return np.zeros(img.shape, bool)
    mask: np.ndarray = (k * mu < R).astype(np.uint8)
    if dilate_px > 0:
        ker = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1, 2 * dilate_px + 1))
        mask = cv2.dilate(mask, ker)
    return mask.astype(bool)
