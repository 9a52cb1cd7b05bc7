"""The render speed-ups must not change a single bit: each fast path against the slow code it replaced.

Every render (``raster="view"`` or ``"tiles"``) goes through these three functions, and the scene
library, the P(safe) training data and docs/RESULTS.md all hold numbers computed with the old code.
"""

import numpy as np
import pytest

from ground_sim.features import Features, _poisson_many, profile
from ground_sim.hashing import poisson
from ground_sim.heightfield import Raster, intersect, refine_roots, remap_flat
from ground_sim.stamp import stamp_raster


def _poisson_many_per_mean(lam: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The old ``_poisson_many``: one ``hashing.poisson`` call per distinct rounded mean."""
    out = np.empty(lam.size, np.int64)
    small = lam < 50
    for lv in np.unique(np.round(lam[small], 6)):
        m = small & (np.round(lam, 6) == lv)
        out[m] = poisson(float(lv), u[m], cap=200)
    big = _poisson_many(lam[~small], u[~small])  # the normal approximation above 50 did not change
    out[~small] = big
    return out


@pytest.mark.parametrize("n", [0, 1, 7, 300, 5000])
def test_poisson_many_equals_a_call_per_mean(n: int) -> None:
    rng = np.random.default_rng(n)
    lam = np.concatenate(
        [
            rng.uniform(0.0, 49.9, n),  # rim boulders: every mean distinct
            np.full(n // 5, 2.5),  # repeated means
            rng.uniform(0.0, 1e-6, n // 10),  # rounds to 0
            rng.uniform(50.0, 80.0, n // 10),  # normal approximation
        ]
    )
    u = rng.uniform(0.0, 1.0, lam.size)
    u[: min(3, u.size)] = [0.0, 1.0 - 2**-53, 0.5][: min(3, u.size)]
    # uniforms exactly on a CDF step of the rounded mean: the side of the search and the rounding both count
    k = np.arange(201)
    for j in range(3, min(n, 60)):
        lv = round(float(lam[j]), 6)
        cdf = np.cumsum(np.exp(-lv + k * np.log(max(lv, 1e-300)) - np.cumsum(np.log(np.maximum(k, 1)))))
        u[j] = cdf[j % 5]
    got = _poisson_many(lam, u)
    assert got.dtype == np.int64
    assert np.array_equal(got, _poisson_many_per_mean(lam, u))


def _intersect_compacting(r, C, d, t0, t1, step, refine=3):
    """The old ``intersect``: every finished ray is compacted away at the step it finishes."""
    n = d.shape[0]
    t = t0.astype(np.float64).copy()
    lo = t.copy()
    hit = np.zeros(n, bool)
    inv = 1.0 / r.cell
    ax, ay, az = np.float32((C[0] - r.x0) * inv), np.float32((C[1] - r.y0) * inv), np.float32(C[2] - r.zref)
    idx = np.arange(n)
    ta = t.astype(np.float32)
    la = ta.copy()
    bx, by = (d[:, 0] * inv).astype(np.float32), (d[:, 1] * inv).astype(np.float32)
    bz, sa, t1a = d[:, 2].astype(np.float32), step.astype(np.float32), t1.astype(np.float32)
    while idx.size:
        f = az + ta * bz - remap_flat(r._H32, ax + ta * bx, ay + ta * by)
        below = f <= 0.0
        if below.any():
            bi = idx[below]
            hit[bi], t[bi], lo[bi] = True, ta[below], la[below]
        nt = ta + sa
        over = ~below & (nt > t1a)
        if over.any():
            oi = idx[over]
            tz = t1[oi]
            fz = C[2] + tz * d[oi, 2] - r.sample_fast(C[0] + tz * d[oi, 0], C[1] + tz * d[oi, 1])
            t[oi], lo[oi], hit[oi] = tz, ta[over], fz <= 0
        keep = ~(below | over)
        idx, la, ta = idx[keep], ta[keep], nt[keep]
        bx, by, bz, sa, t1a = bx[keep], by[keep], bz[keep], sa[keep], t1a[keep]
    return refine_roots(r, C, d, t, lo, hit, refine), hit  # the refinement did not change


def test_intersect_marches_like_the_compacting_loop() -> None:
    """Rays finish over many steps (spikes, slopes, misses): the same brackets, hits and refined roots."""
    rng = np.random.default_rng(5)
    ny, nx = 120, 140
    H = 0.3 * rng.standard_normal((ny, nx)) + np.linspace(0.0, 6.0, nx)[None, :]
    H[rng.integers(0, ny, 60), rng.integers(0, nx, 60)] += rng.uniform(1.0, 8.0, 60)  # early hits
    r = Raster(-3.0, 2.0, 0.25, H)
    C = np.array([14.0, 17.0, 40.0])
    n = 20_000
    tx, ty = rng.uniform(-2.0, 32.0, n), rng.uniform(3.0, 31.0, n)  # some targets outside: misses
    d = np.stack([tx - C[0], ty - C[1], np.full(n, -C[2])], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t0 = (C[2] - rng.uniform(12.0, 20.0, n)) / -d[:, 2]
    t1 = (C[2] - rng.uniform(-1.0, 4.0, n)) / -d[:, 2]  # some end above the ground: the probe at t1
    step = rng.uniform(0.1, 0.6, n)
    for refine in (1, 3):
        t_ref, hit_ref = _intersect_compacting(r, C, d, t0, t1, step, refine)
        assert 0.05 < hit_ref.mean() < 0.99  # both outcomes are exercised
        t, hit = intersect(r, C, d, t0, t1, step, refine)
        assert np.array_equal(hit, hit_ref)
        assert t.tobytes() == t_ref.tobytes()


@pytest.mark.parametrize("kind", ["crater", "boulder"])
def test_big_feature_stamp_equals_per_cell_parameters(kind: str) -> None:
    """A feature wider than BIG cells is stamped on its window with its parameters broadcast: same bits."""
    cell = 0.05
    f = Features(
        np.array([1.3, 4.1, 2.2]),
        np.array([2.0, 3.7, 0.4]),
        np.array([3.0, 5.5, 4.2]),  # patches of 120-220 cells: all take the per-feature path
        np.array([0.6, 0.9, 0.7]),
        np.array([0.0, 0.37, 1.0]) if kind == "crater" else np.zeros(3),
        kind,
    )
    nx, ny = 130, 110
    x0, y0 = -0.7, -0.3
    h, a = np.zeros((ny, nx)), np.zeros((ny, nx))
    stamp_raster(f, x0, y0, cell, nx, ny, h, a)
    h_ref, a_ref = np.zeros((ny, nx)), np.zeros((ny, nx))
    for i in range(len(f)):  # the old loop: one window per feature, an index per cell
        r = f.reach[i]
        c0 = max(int(np.floor((f.x[i] - r - x0) / cell)), 0)
        c1 = min(int(np.ceil((f.x[i] + r - x0) / cell)), nx - 1)
        r0 = max(int(np.floor((f.y[i] - r - y0) / cell)), 0)
        r1 = min(int(np.ceil((f.y[i] + r - y0) / cell)), ny - 1)
        gx = x0 + np.arange(c0, c1 + 1) * cell - f.x[i]
        gy = y0 + np.arange(r0, r1 + 1) * cell - f.y[i]
        rr = (gx[None, :] ** 2 + gy[:, None] ** 2) / (0.5 * f.d[i]) ** 2
        dh, da = profile(f, rr, np.full(rr.shape, i))
        h_ref[r0 : r1 + 1, c0 : c1 + 1] += dh
        a_ref[r0 : r1 + 1, c0 : c1 + 1] += da
    assert np.count_nonzero(h_ref) > 1000
    assert h.tobytes() == h_ref.tobytes() and a.tobytes() == a_ref.tobytes()
