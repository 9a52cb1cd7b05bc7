"""Filling small DEM gaps by first-order normalized convolution (box filters, O(1) per pixel).

A pixel without a recovered elevation gets the value at its centre of the
least-squares plane through the valid elevations in the ``(2r+1)^2`` square
around it (the same closed-form box-sum solver as the footprint slope,
:func:`flight_sw.slope.plane_fit`, eq. 4.11/4.12)::

    z_f(x) = p_x * 0 + q_x * 0 + r_x,   (p, q, r) = argmin sum_{N(x), valid} (p u + q v + r - z)^2

but only where at least ``min_frac`` of the neighbourhood is valid: a gap
narrower than about the window (surrounded by measured ground) is
interpolated, a large hole stays NaN and is later mapped unsafe ("unknown is
unsafe", mapping.combine). A plane - not a local mean - is used so that a
filled patch on a slope keeps that slope: a mean would make it a flat
terrace and hide a steep wall from the hazard stage.
"""

from __future__ import annotations

import numpy as np

from .slope import plane_fit


def fill_small_gaps(z: np.ndarray, radius_px: int, min_frac: float = 0.3) -> np.ndarray:
    """``z`` (float, NaN = unknown) with gaps filled where enough of the neighbourhood is known.

    Returns a new float32 array; valid input values are unchanged. ``radius_px <= 0``
    returns a copy.
    """
    z = np.asarray(z, dtype=np.float32)
    out = z.copy()
    if radius_px <= 0:
        return out
    valid = np.isfinite(z)
    if valid.all() or not valid.any():
        return out
    k = 2 * int(radius_px) + 1
    # only cells within the radius of a valid one can be filled: work on that bounding box
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    r = int(radius_px)
    y0, y1 = max(0, rows[0] - r), min(z.shape[0], rows[-1] + r + 1)
    x0, x1 = max(0, cols[0] - r), min(z.shape[1], cols[-1] + r + 1)
    _, zc = plane_fit(z[y0:y1, x0:x1], 1.0, float(k), min_fraction=min_frac)
    take = ~valid[y0:y1, x0:x1] & np.isfinite(zc)
    out[y0:y1, x0:x1][take] = zc[take]
    return out
