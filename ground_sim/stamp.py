"""Add feature shapes to heights: on a regular raster (stamping) or at scattered points.

Raster: small features are stamped in vectorised batches of equal-size patches and
accumulated with ``np.bincount``; large ones (patch > ``BIG`` cells) are evaluated on
their clipped window one by one (there are few). Points: features are tested against
tiles of points so the cost is (points x nearby features), not (points x all).
"""

from __future__ import annotations

import numpy as np

from ground_sim.features import Features, height_profile, profile

BIG = 48  # patch side (cells) above which a feature gets its own window
BATCH = 3_000_000  # max patch elements per vectorised batch


def stamp_raster(
    f: Features, x0: float, y0: float, cell: float, nx: int, ny: int, height: np.ndarray, albedo: np.ndarray | None
) -> None:
    """Add the features' height/albedo changes to ``height``/``albedo`` (ny x nx) in place (``albedo`` None:
    heights only, the same height bytes)."""
    if not len(f):
        return
    reach = f.reach
    side = np.ceil(2 * reach / cell).astype(np.int64) + 2
    small = np.nonzero(side <= BIG)[0]
    flat: list[np.ndarray] = []
    dh: list[np.ndarray] = []
    da: list[np.ndarray] = []
    for p in np.unique(side[small]):
        sel = small[side[small] == p]
        for chunk in np.array_split(sel, max(1, int(np.ceil(sel.size * p * p / BATCH)))):
            _stamp_batch(f, chunk, int(p), x0, y0, cell, nx, ny, flat, dh, None if albedo is None else da)
    if flat:
        # one scatter-add over the whole raster for all batches (a bincount per batch costs a full raster pass)
        flat_all = np.concatenate(flat)
        height += np.bincount(flat_all, np.concatenate(dh), minlength=nx * ny).reshape(ny, nx)
        if albedo is not None and (f.kind == "boulder" or np.any(f.s[small] < 0.9)):
            albedo += np.bincount(flat_all, np.concatenate(da), minlength=nx * ny).reshape(ny, nx)
    for i in np.nonzero(side > BIG)[0]:
        r = reach[i]
        c0 = max(int(np.floor((f.x[i] - r - x0) / cell)), 0)
        c1 = min(int(np.ceil((f.x[i] + r - x0) / cell)), nx - 1)
        r0 = max(int(np.floor((f.y[i] - r - y0) / cell)), 0)
        r1 = min(int(np.ceil((f.y[i] + r - y0) / cell)), ny - 1)
        if c1 < c0 or r1 < r0:
            continue
        gx = x0 + np.arange(c0, c1 + 1) * cell - f.x[i]
        gy = y0 + np.arange(r0, r1 + 1) * cell - f.y[i]
        rr = (gx[None, :] ** 2 + gy[:, None] ** 2) / (0.5 * f.d[i]) ** 2
        # one index broadcast over the window: the feature's parameters are gathered once, not per cell
        if albedo is None:
            height[r0 : r1 + 1, c0 : c1 + 1] += height_profile(f, rr, np.full((1, 1), i))
            continue
        dh_i, da_i = profile(f, rr, np.full((1, 1), i))
        height[r0 : r1 + 1, c0 : c1 + 1] += dh_i
        albedo[r0 : r1 + 1, c0 : c1 + 1] += da_i


def _stamp_batch(f, sel, p, x0, y0, cell, nx, ny, flat_out, dh_out, da_out):
    """Append the flat raster indices and height/albedo changes of features ``sel`` (patch side p)."""
    fx, fy, reach = f.x[sel], f.y[sel], f.reach[sel]
    c0 = np.floor((fx - reach - x0) / cell).astype(np.int64)
    r0 = np.floor((fy - reach - y0) / cell).astype(np.int64)
    a = np.arange(p)
    cols = c0[:, None] + a  # (k, p)
    rows = r0[:, None] + a
    inv = (1.0 / (0.25 * f.d[sel] ** 2))[:, None]
    # the squared normalised distance split per axis on (k, p) rows, a cell outside the raster made infinitely far:
    # one (k, p, p) sum and one comparison instead of five, the patch's costliest part
    ux = x0 + cols * cell - fx[:, None]
    ux *= ux
    ux *= inv
    ux[(cols < 0) | (cols >= nx)] = np.inf
    uy = y0 + rows * cell - fy[:, None]
    uy *= uy
    uy *= inv
    uy[(rows < 0) | (rows >= ny)] = np.inf
    rr = uy[:, :, None] + ux[:, None, :]
    ok = rr < ((reach / (0.5 * f.d[sel])) ** 2)[:, None, None]
    kk, ii, jj = np.nonzero(ok)
    flat_out.append(rows[kk, ii] * nx + cols[kk, jj])
    idx = sel[kk]
    r2 = rr[ok]
    if da_out is None:
        dh_out.append(height_profile(f, r2, idx))
        return
    dh, da = profile(f, r2, idx)
    dh_out.append(dh)
    da_out.append(da)


def stamp_points(f: Features, x: np.ndarray, y: np.ndarray, tile: float = 32.0) -> tuple[np.ndarray, np.ndarray]:
    """Height and albedo changes of ``f`` at scattered points (flat arrays)."""
    dh = np.zeros(x.shape)
    da = np.zeros(x.shape)
    if not len(f) or not x.size:
        return dh, da
    tx = np.floor(x / tile).astype(np.int64)
    ty = np.floor(y / tile).astype(np.int64)
    key = tx * 1_000_003 + ty
    order = np.argsort(key, kind="stable")
    uk, start = np.unique(key[order], return_index=True)
    bounds = np.append(start, order.size)
    reach = f.reach
    for t in range(uk.size):
        pts = order[bounds[t] : bounds[t + 1]]
        px, py = x[pts], y[pts]
        near = np.nonzero(
            (f.x + reach >= px.min())
            & (f.x - reach <= px.max())
            & (f.y + reach >= py.min())
            & (f.y - reach <= py.max())
        )[0]
        for chunk in np.array_split(near, max(1, int(np.ceil(near.size * pts.size / BATCH)))):
            if not chunk.size:
                continue
            rr = (px[:, None] - f.x[chunk][None, :]) ** 2 + (py[:, None] - f.y[chunk][None, :]) ** 2
            rr /= 0.25 * f.d[chunk][None, :] ** 2
            h, a = profile(f, rr, np.broadcast_to(chunk[None, :], rr.shape))
            dh[pts] += h.sum(axis=1)
            da[pts] += a.sum(axis=1)
    return dh, da
