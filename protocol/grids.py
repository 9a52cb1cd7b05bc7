"""The compact Result's grids: quantisation to and from the wire (docs/protocol.md, "Result").

* P(safe) as uint8: ``v = round(254 p)`` for p in [0, 1], 255 = outside (NaN);
  the quantisation step is 1/254, so the error is at most 1/508. Decimated by an
  integer step k, a block's value is the *minimum* P(safe) of its cells (finite
  ones; outside if none): conservative, a block is never safer than its worst cell.
* Elevation as int16 units of ``u`` centimetres above an offset: ``v = round(100 (z - offset) / u)``,
  saturated to [-32767, 32767], -32768 = no elevation; the offset is the median
  elevation rounded to a metre, so the grid spans +-327 u m around it at u/2 cm error.
  ``u = 1`` keeps every centimetre; a serial link sends ``u = 10``, well under the DEM's own error
  (0.17-0.85 m mean on the thesis tables), which halves the compressed grid (docs/benchmarks/protocol.md).
* Decimation of the elevation grid by an integer step k: the mean of the finite
  values in each k x k block of grid cells (a block with none is "no elevation").
  Block ``[i, j]`` is centred at ``origin + ((k - 1) / 2 + k j) cell`` in x and the
  mirror in y (rows toward -Y).

Both the flight side (encoding) and the ground side (decoding, scoring) use these.
"""

from __future__ import annotations

import math

import numpy as np

PSAFE_OUTSIDE = 255
PSAFE_SCALE = 254
ELEVATION_NONE = -32768
ELEVATION_SCALE = 100.0  # wire units per metre (centimetres)


def psafe_to_wire(psafe: np.ndarray, step: int = 1, coarse: np.ndarray | None = None, levels: int = 16) -> np.ndarray:
    """float P(safe), NaN outside -> uint8 (0..254, 255 outside), decimated by ``step`` (block minimum).

    ``coarse`` (bool, the grid's shape): cells whose P(safe) is sent to ``1 / levels`` only, rounded to the
    nearest level before the block minimum (still ``v / 254`` on the wire). The flight sends the cells it
    did not call safe so: their state decides, and their P(safe) in 17 values compresses to a smaller Result
    (docs/protocol.md)."""
    if coarse is not None:
        if not 1 <= int(levels) <= PSAFE_SCALE:
            raise ValueError(f"psafe_to_wire: levels must be in [1, {PSAFE_SCALE}], got {levels!r}")
        p0 = np.asarray(psafe, np.float32)
        psafe = np.where(np.asarray(coarse, bool), np.rint(p0 * np.float32(levels)) / np.float32(levels), p0)
    p = decimate_min(psafe, step)
    q = np.rint(np.clip(np.nan_to_num(p, nan=0.0), 0.0, 1.0) * PSAFE_SCALE).astype(np.uint8)
    q[~np.isfinite(p)] = PSAFE_OUTSIDE
    return q


def psafe_from_wire(q: np.ndarray) -> np.ndarray:
    """uint8 wire P(safe) -> float32 in [0, 1], NaN outside."""
    q = np.asarray(q, np.uint8)
    out = q.astype(np.float32) / PSAFE_SCALE
    out[q == PSAFE_OUTSIDE] = np.nan
    return out


def _blocks(a: np.ndarray, k: int) -> np.ndarray:
    """``a`` padded with NaN to multiples of k, as (H/k, k, W/k, k) blocks."""
    h, w = a.shape
    H, W = -(-h // k), -(-w // k)
    pad = np.full((H * k, W * k), np.nan, np.float32)
    pad[:h, :w] = a
    return pad.reshape(H, k, W, k)


def decimate_min(a: np.ndarray, k: int) -> np.ndarray:
    """Minimum of the finite values in each k x k block (NaN where a block has none)."""
    a = np.asarray(a, np.float32)
    if k == 1:
        return a.copy()
    blocks = _blocks(a, k)
    out = np.where(np.isfinite(blocks), blocks, np.inf).min(axis=(1, 3))
    out[np.isinf(out)] = np.nan
    return out.astype(np.float32)


def decimate_mean(a: np.ndarray, k: int) -> np.ndarray:
    """Mean of the finite values in each k x k block (NaN where a block has none); shape ceil(H/k), ceil(W/k)."""
    a = np.asarray(a, np.float32)
    if k == 1:
        return a.copy()
    blocks = _blocks(a, k)
    H, W = blocks.shape[0], blocks.shape[2]
    ok = np.isfinite(blocks)
    n = ok.sum(axis=(1, 3))
    s = np.where(ok, blocks, 0.0).sum(axis=(1, 3), dtype=np.float64)
    out = np.full((H, W), np.nan, np.float32)
    np.divide(s, n, out=out, where=n > 0, casting="unsafe")
    return out


def filled_to_wire(filled: np.ndarray, step: int = 1) -> np.ndarray:
    """bool cells whose elevation is a gap fill -> uint8 0/1 decimated by ``step``: 1 where any cell of
    the k x k block is one (the block's mean elevation then leans on a fill)."""
    f = np.asarray(filled, bool)
    if step == 1:
        return f.astype(np.uint8)
    blocks = _blocks(f.astype(np.float32), step)
    return (np.nan_to_num(blocks, nan=0.0).max(axis=(1, 3)) > 0).astype(np.uint8)


def elevation_to_wire(elevation: np.ndarray, step: int = 1, unit_cm: int = 1) -> tuple[np.ndarray, float]:
    """float elevation (m, NaN = none) -> (int16 grid in ``unit_cm`` cm, decimated by ``step``; offset in m)."""
    z = decimate_mean(elevation, step)
    finite = np.isfinite(z)
    offset = float(round(float(np.median(z[finite])))) if finite.any() else 0.0
    scale = ELEVATION_SCALE / unit_cm
    v = np.clip(np.rint((np.nan_to_num(z, nan=offset) - offset) * scale), -32767, 32767).astype(np.int16)
    v[~finite] = ELEVATION_NONE
    return v, offset


def elevation_from_wire(v: np.ndarray, offset_m: float, unit_cm: int = 1) -> np.ndarray:
    """int16 wire elevation in ``unit_cm`` cm -> float32 metres, NaN where none."""
    v = np.asarray(v, np.int16)
    out = (v.astype(np.float64) * (unit_cm / ELEVATION_SCALE) + offset_m).astype(np.float32)
    out[v == ELEVATION_NONE] = np.nan
    return out


def decimated_geometry(origin_xy: tuple[float, float], cell_m: float, step: int) -> tuple[tuple[float, float], float]:
    """Origin (centre of cell [0, 0]) and cell size of a grid decimated by ``step``."""
    half = (step - 1) / 2.0 * cell_m
    return (origin_xy[0] + half, origin_xy[1] - half), cell_m * step


def cells_at(
    x: np.ndarray, y: np.ndarray, origin_xy: tuple[float, float], cell_m: float, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest grid cell ``(i, j)`` of world points and whether it lies on the grid."""
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise ValueError(f"grid cell must be > 0, got {cell_m}")
    j = np.rint((np.asarray(x, np.float64) - origin_xy[0]) / cell_m)
    i = np.rint((origin_xy[1] - np.asarray(y, np.float64)) / cell_m)
    ok = np.isfinite(i) & np.isfinite(j) & (i >= 0) & (j >= 0) & (i < shape[0]) & (j < shape[1])
    return np.where(ok, i, 0).astype(np.intp), np.where(ok, j, 0).astype(np.intp), ok
