"""Shadow detection (thesis sec 4.4.1, eq. 4.9): pixels darker than ``(mu + sigma) / 2``."""

from __future__ import annotations

import numpy as np


def shadow_threshold(img: np.ndarray) -> float:
    """Eq. 4.9: half the sum of the image's mean and standard deviation."""
    I = np.asarray(img, dtype=np.float64)
    return float((I.mean() + I.std()) / 2.0)


def shadow_mask(img: np.ndarray, threshold: float | None = None) -> np.ndarray:
    """Boolean shadow map: intensity strictly below the eq. 4.9 threshold (or ``threshold``)."""
    t = shadow_threshold(img) if threshold is None else threshold
    return np.asarray(img) < t
