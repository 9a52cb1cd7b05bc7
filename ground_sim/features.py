"""Craters and boulders: power-law populations generated lazily per spatial cell.

Each size class ``[D_k, 2 D_k)`` has its own square cell grid (cell ~ a few D_k);
the number of features in a cell is Poisson with mean ``cell_area * (N(>D_k) - N(>2D_k))``
and every attribute is a hash of (seed, stream, class, cell, index) - so the
population seen through any window is the same (scenes.md: "generate craters lazily,
per spatial cell, from a deterministic hash"). Diameters inside a class follow the
truncated power law of the cumulative SFD ``N(>D) = A D^-b`` by inverse CDF.

Shapes (heights added to the base relief), r = distance / radius:

* crater, fresh (MPD/PANGU model, scenes.md sec. 1): parabolic bowl from depth
  ``-H`` (``H = d/D * D``) up to a rim ``+Hr`` at r=1, ejecta ``Hr r^-3`` outside,
  tapered to zero at r = 2; degraded: a shallow smooth bowl ``-0.04 D (1 - r^2/1.44)^2``.
  A crater with degradation state ``s`` is ``(1-s) fresh + s degraded``.
* boulder: half-ellipsoid ``H sqrt(1 - r^2)``, H ~ 0.5 D (Golombek).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ground_sim.hashing import hash_u64, poisson, uniform

BBox = tuple[float, float, float, float]  # x0, y0, x1, y1 (m)

CRATER_STREAM, BOULDER_STREAM, RIM_BOULDER_STREAM, FIELD_STREAM, FIELD_BOULDER_STREAM = 2, 3, 4, 5, 6
CRATER_REACH = 2.0  # influence radius / crater radius (ejecta cut)
BOULDER_REACH = 1.0
RIM_RATIO = 0.036 / 0.196  # fresh crater rim height / depth (the MPD ratio of crater_profile)
THIN = 5  # hash field of the thinning draw (fields 0-4 are position, size and shape)
POISSON_CAP = 200  # largest count of _poisson_many's exact draws (means < 50)
POISSON_ROWS = 2048  # CDF rows per block in _poisson_many (2048 x 201 float64: 3.3 MB)


@dataclass(frozen=True)
class Features:
    """Flat arrays of features of one kind: centre, diameter, height scale, state."""

    x: np.ndarray
    y: np.ndarray
    d: np.ndarray  # diameter (m)
    h: np.ndarray  # crater depth or boulder height (m)
    s: np.ndarray  # crater degradation state in [0,1] (0 fresh); unused for boulders
    kind: str  # "crater" or "boulder"

    @property
    def reach(self) -> np.ndarray:
        return 0.5 * self.d * (CRATER_REACH if self.kind == "crater" else BOULDER_REACH)

    def __len__(self) -> int:
        return int(self.x.size)

    @staticmethod
    def concat(parts: list[Features], kind: str) -> Features:
        if not parts:
            e = np.zeros(0)
            return Features(e, e, e, e, e, kind)
        x, y, d, h, s = (np.concatenate([getattr(p, f) for p in parts]) for f in "xydhs")
        return Features(x, y, d, h, s, kind)

    def select(self, m: np.ndarray) -> Features:
        return Features(self.x[m], self.y[m], self.d[m], self.h[m], self.s[m], self.kind)


@dataclass(frozen=True)
class PowerLaw:
    """Cumulative size-frequency distribution ``N(>D) = coef * D^-exponent`` per m^2 on [d_min, d_max]."""

    coef: float
    exponent: float
    d_min: float
    d_max: float

    def classes(self) -> list[tuple[int, float, float]]:
        out, k, lo = [], 0, self.d_min
        while lo < self.d_max:
            out.append((k, lo, min(2 * lo, self.d_max)))
            k, lo = k + 1, 2 * lo
        return out

    def density(self, lo: float, hi: float) -> float:
        return self.coef * (lo**-self.exponent - hi**-self.exponent)

    def sample_d(self, lo: float, hi: float, u: np.ndarray) -> np.ndarray:
        """Inverse CDF of the truncated power law on [lo, hi)."""
        b = self.exponent
        return lo * (1.0 - u * (1.0 - (hi / lo) ** -b)) ** (-1.0 / b)


@dataclass(frozen=True)
class RadialProfile:
    """Density factor against distance from the origin (the nominal landing site): piecewise linear.

    ``knots`` = ((r0, f0), (r1, f1), ...) with r ascending; constant beyond the ends. A
    population with a profile is drawn at ``max(f) x`` its density and each feature is kept
    with probability ``f(r) / max(f)`` (a hashed draw, so any window sees the same features).
    """

    knots: tuple[tuple[float, float], ...]

    @property
    def peak(self) -> float:
        return max(f for _, f in self.knots)

    def factor(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r = np.hypot(x, y)
        return np.interp(r, [k[0] for k in self.knots], [k[1] for k in self.knots])


def _thin(f: Features, keep_u: np.ndarray, profile: RadialProfile | None) -> Features:
    if profile is None:
        return f
    return f.select(keep_u * profile.peak < profile.factor(f.x, f.y))


def _scaled(sfd: PowerLaw, profile: RadialProfile | None) -> PowerLaw:
    if profile is None:
        return sfd
    return PowerLaw(sfd.coef * profile.peak, sfd.exponent, sfd.d_min, sfd.d_max)


def _cells(bbox: BBox, cell: float, margin: float):
    x0, y0, x1, y1 = bbox
    i0, i1 = int(np.floor((x0 - margin) / cell)), int(np.floor((x1 + margin) / cell))
    j0, j1 = int(np.floor((y0 - margin) / cell)), int(np.floor((y1 + margin) / cell))
    ci, cj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1))
    return ci.ravel(), cj.ravel()


def _populate(
    seed: int,
    stream: int,
    k: int,
    lo: float,
    hi: float,
    sfd: PowerLaw,
    bbox: BBox,
    reach_factor: float,
    mean_per_cell: float = 1.5,
):
    """Cell-hashed positions and diameters of class k overlapping ``bbox`` (+ reach)."""
    dens = sfd.density(lo, hi)
    if dens <= 0:
        return None
    cell = float(np.sqrt(mean_per_cell / dens))
    ci, cj = _cells(bbox, cell, reach_factor * hi / 2)
    if ci.size > 4_000_000:
        raise MemoryError("feature window too large for this size class")
    counts = poisson(dens * cell * cell, uniform(seed, stream, k, ci, cj, -1))
    if counts.sum() == 0:
        return None
    rep = np.repeat(np.arange(ci.size), counts)
    idx = np.arange(rep.size) - np.repeat(np.cumsum(counts) - counts, counts)
    ci, cj = ci[rep], cj[rep]
    u = [uniform(seed, stream, k, ci, cj, idx, f) for f in range(5)]
    x = (ci + u[0]) * cell
    y = (cj + u[1]) * cell
    d = sfd.sample_d(lo, hi, u[2])
    return x, y, d, u[3], u[4], (ci, cj, idx)


def craters_in(
    seed: int, sfd: PowerLaw, bbox: BBox, d_min: float, degradation: float, profile: RadialProfile | None = None
) -> Features:
    """Craters with diameter >= ``d_min`` whose influence reaches ``bbox`` = (x0, y0, x1, y1)."""
    parts = []
    g = float(np.clip(degradation, 0.02, 0.98))
    gen = _scaled(sfd, profile)
    for k, lo, hi in sfd.classes():
        if hi <= d_min:
            continue
        r = _populate(seed, CRATER_STREAM, k, lo, hi, gen, bbox, CRATER_REACH)
        if r is None:
            continue
        x, y, d, u3, u4, (ci, cj, idx) = r
        s = u3 ** ((1 - g) / g)  # g -> 0: all fresh, g -> 1: all worn
        dd = np.where(
            d >= 400,
            0.21,
            np.where(d >= 200, 0.17, np.where(d >= 100, 0.15, np.where(d >= 40, 0.13, np.where(d >= 10, 0.11, 0.10)))),
        )  # Stopar 2017 fresh d/D
        h = (dd + 0.02 * (u4 - 0.5)) * d
        f = Features(x, y, d, h, s, "crater")
        keep_u = uniform(seed, CRATER_STREAM, k, ci, cj, idx, THIN) if profile is not None else np.zeros(0)
        f, keep_u = _select2(f, keep_u, (d >= d_min) & _touches(f, bbox))
        parts.append(_thin(f, keep_u, profile))
    return Features.concat(parts, "crater")


def _select2(f: Features, u: np.ndarray, m: np.ndarray) -> tuple[Features, np.ndarray]:
    return f.select(m), (u[m] if u.size else u)


def boulders_in(
    seed: int,
    sfd: PowerLaw,
    bbox: BBox,
    d_min: float,
    craters: Features,
    rim_per_crater_m2: float,
    profile: RadialProfile | None = None,
) -> Features:
    """Background boulders plus boulders strewn around fresh craters (denser near rims)."""
    parts = []
    gen = _scaled(sfd, profile)
    for k, lo, hi in sfd.classes():
        if hi <= d_min:
            continue
        r = _populate(seed, BOULDER_STREAM, k, lo, hi, gen, bbox, BOULDER_REACH)
        if r is None:
            continue
        x, y, d, u3, _, (ci, cj, idx) = r
        f = Features(x, y, d, d * (0.35 + 0.25 * u3), np.zeros_like(d), "boulder")
        keep_u = uniform(seed, BOULDER_STREAM, k, ci, cj, idx, THIN) if profile is not None else np.zeros(0)
        f, keep_u = _select2(f, keep_u, (d >= d_min) & _touches(f, bbox))
        parts.append(_thin(f, keep_u, profile))
    # Rim boulders: fresh craters >= 8 m shed blocks into an annulus 0.9-1.8 R.
    if rim_per_crater_m2 > 0 and len(craters):
        fresh = craters.select((craters.d >= 8.0) & (craters.s < 0.35))
        if len(fresh):
            area = np.pi * ((0.9 * fresh.d) ** 2 - (0.45 * fresh.d) ** 2)
            key = np.round(fresh.x * 64).astype(np.int64), np.round(fresh.y * 64).astype(np.int64)
            lam = rim_per_crater_m2 * area * (1 - fresh.s / 0.35)
            u0 = uniform(seed, RIM_BOULDER_STREAM, key[0], key[1], -1)
            n = (
                np.array([poisson(float(l), np.array([u]), cap=4000)[0] for l, u in zip(lam, u0)])
                if lam.size < 64
                else _poisson_many(lam, u0)
            )
            if n.sum():
                j = np.repeat(np.arange(len(fresh)), n)
                i = np.arange(j.size) - np.repeat(np.cumsum(n) - n, n)
                u = [uniform(seed, RIM_BOULDER_STREAM, key[0][j], key[1][j], i, f) for f in range(4)]
                rr = 0.5 * fresh.d[j] * (0.9 + 0.9 * u[0] ** 1.5)
                th = 2 * np.pi * u[1]
                d = np.minimum(sfd.sample_d(sfd.d_min, sfd.d_max, u[2]), 0.2 * fresh.d[j])
                b = Features(
                    fresh.x[j] + rr * np.sin(th),
                    fresh.y[j] + rr * np.cos(th),
                    d,
                    d * (0.35 + 0.25 * u[3]),
                    np.zeros(j.size),
                    "boulder",
                )
                parts.append(b.select((d >= d_min) & _touches(b, bbox)))
    return Features.concat(parts, "boulder")


def field_boulders(
    seed: int,
    sfd: PowerLaw,
    fx: np.ndarray,
    fy: np.ndarray,
    fr: np.ndarray,
    keys: np.ndarray,
    bbox: BBox,
    d_min: float,
) -> Features:
    """Boulders of boulder fields: disks (centre fx, fy, radius fr) each holding its own population.

    Per field and size class the count is Poisson(pi r^2 x class density) and positions are
    uniform over the disk; every draw hashes (seed, field key, class, index), so a window
    sees the same boulders whatever its size (fields are generated whole, then clipped).
    """
    parts: list[Features] = []
    if fx.size == 0:
        return Features.concat(parts, "boulder")
    area = np.pi * fr * fr
    for k, lo, hi in sfd.classes():
        if hi <= d_min:
            continue
        lam = area * sfd.density(lo, hi)
        n = _poisson_many(lam, uniform(seed, FIELD_BOULDER_STREAM, keys, k, -1))
        if n.sum() == 0:
            continue
        j = np.repeat(np.arange(fx.size), n)
        i = np.arange(j.size) - np.repeat(np.cumsum(n) - n, n)
        u = [uniform(seed, FIELD_BOULDER_STREAM, keys[j], k, i, f) for f in range(4)]
        rr = fr[j] * np.sqrt(u[0])
        th = 2 * np.pi * u[1]
        d = sfd.sample_d(lo, hi, u[2])
        b = Features(
            fx[j] + rr * np.sin(th), fy[j] + rr * np.cos(th), d, d * (0.35 + 0.25 * u[3]), np.zeros(j.size), "boulder"
        )
        parts.append(b.select((d >= d_min) & _touches(b, bbox)))
    return Features.concat(parts, "boulder")


def random_fields(
    seed: int, per_km2: float, radius_m: float, bbox: BBox
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centres, radii (uniform in 0.5-1.5 x ``radius_m``) and keys of random boulder fields touching ``bbox``."""
    dens = per_km2 * 1e-6
    e = np.zeros(0)
    if dens <= 0:
        return e, e, e, e.astype(np.int64)
    cell = float(np.sqrt(1.5 / dens))
    ci, cj = _cells(bbox, cell, 1.5 * radius_m)
    counts = poisson(dens * cell * cell, uniform(seed, FIELD_STREAM, ci, cj, -1))
    if counts.sum() == 0:
        return e, e, e, e.astype(np.int64)
    rep = np.repeat(np.arange(ci.size), counts)
    idx = np.arange(rep.size) - np.repeat(np.cumsum(counts) - counts, counts)
    ci, cj = ci[rep], cj[rep]
    u = [uniform(seed, FIELD_STREAM, ci, cj, idx, f) for f in range(3)]
    x, y = (ci + u[0]) * cell, (cj + u[1]) * cell
    r = radius_m * (0.5 + u[2])
    keys = (hash_u64(ci, cj, idx) >> np.uint64(2)).astype(np.int64)
    x0, y0, x1, y1 = bbox
    m = (x + r >= x0) & (x - r <= x1) & (y + r >= y0) & (y - r <= y1)
    return x[m], y[m], r[m], keys[m]


def _poisson_many(lam: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Poisson draws with per-item means: exact inverse CDF for small means, normal approximation above 50."""
    out = np.empty(lam.size, np.int64)
    small = lam < 50
    if np.any(small):
        # hashing.poisson(round(lam, 6), u, cap=200) per item, as one table of CDF rows (one per
        # distinct mean: rim boulders' means are all distinct, and a call per mean cost ~15 us);
        # the same float operations in the same order, so the same counts to the bit
        lv, inv = np.unique(np.round(lam[small], 6), return_inverse=True)
        us = u[small]
        k = np.arange(POISSON_CAP + 1)
        lfact = np.cumsum(np.log(np.maximum(k, 1)))
        loglv = np.log(np.maximum(lv, 1e-300))
        cnt = np.empty(us.size, np.int64)
        for c0 in range(0, lv.size, POISSON_ROWS):
            c1 = min(c0 + POISSON_ROWS, lv.size)
            cdf = np.cumsum(np.exp(-lv[c0:c1, None] + k[None, :] * loglv[c0:c1, None] - lfact[None, :]), axis=1)
            m = (inv >= c0) & (inv < c1)
            # searchsorted(cdf, u, "right") on a non-decreasing CDF = the number of entries <= u
            cnt[m] = (cdf[inv[m] - c0] <= us[m, None]).sum(axis=1)
        out[small] = cnt.clip(0, POISSON_CAP)
    if np.any(~small):
        from statistics import NormalDist

        z = np.array([NormalDist().inv_cdf(min(max(x, 1e-12), 1 - 1e-12)) for x in u[~small]])
        out[~small] = np.maximum(np.rint(lam[~small] + np.sqrt(lam[~small]) * z), 0).astype(np.int64)
    return out


def _touches(f: Features, bbox: BBox) -> np.ndarray:
    x0, y0, x1, y1 = bbox
    r = f.reach
    return (f.x + r >= x0) & (f.x - r <= x1) & (f.y + r >= y0) & (f.y - r <= y1)


def crater_profile(r2: np.ndarray, d: np.ndarray, h: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Height change at squared normalised radius r2 = (dist/R)^2; zero for r >= 2.

    fresh: ``-H + (H + Hr) r^2`` inside, ``Hr r^-3 (1 - (r^2-1)/3)^2`` outside (C1 taper to 0
    at r = 2), ``Hr = (0.036/0.196) H`` (MPD ratio); worn: ``-0.04 D (1 - r^2/1.44)^2``.
    ``d``, ``h``, ``s`` broadcast against ``r2``.
    """
    # in place, without a fractional power: the renderer's costliest function, 2.2x faster (docs/benchmarks/render.md)
    r2c = np.clip(r2, 1.0, 4.0)
    fresh = 4.0 - r2c  # 3 x taper
    fresh *= fresh
    fresh *= RIM_RATIO * h
    fresh /= r2c * np.sqrt(r2c) * 9.0
    inside = r2 < 1.0
    if inside.any():
        hi = np.broadcast_to(h, r2.shape)[inside]
        fresh[inside] = (hi + RIM_RATIO * hi) * r2[inside] - hi
    worn = 1.0 - r2 / 1.44
    np.maximum(worn, 0.0, out=worn)
    worn *= worn
    worn *= -0.04 * d
    worn -= fresh
    worn *= s
    worn += fresh
    return worn


def crater_albedo(r2: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Relative albedo change: fresh ejecta is brighter (scenes.md: highlands/ejecta 0.25-0.30).

    ``0.12 (1 - s)^3 halo``, halo ``0.3 + 0.7 r^2`` inside, ``clip((4 - r^2)/3, 0, 1)`` outside."""
    halo = (4.0 - r2) / 3.0
    np.clip(halo, 0.0, 1.0, out=halo)
    inside = r2 < 1.0
    if inside.any():
        halo[inside] = 0.3 + 0.7 * r2[inside]
    fade = 1.0 - s
    fade = fade * fade * fade * 0.12
    return fade * halo


def boulder_profile(r2: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Half-ellipsoid boulder of height h: ``H sqrt(1 - r^2)``."""
    return h * np.sqrt(np.clip(1.0 - r2, 0.0, None))


def height_profile(f: Features, r2: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """The height change of :func:`profile` alone (the same bytes)."""
    if f.kind == "crater":
        return crater_profile(r2, f.d[idx], f.h[idx], f.s[idx])
    return boulder_profile(r2, f.h[idx])


def profile(f: Features, r2: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(height change, relative albedo change) of features ``idx`` at squared normalised radii r2."""
    if f.kind == "crater":
        return crater_profile(r2, f.d[idx], f.h[idx], f.s[idx]), crater_albedo(r2, f.s[idx])
    return boulder_profile(r2, f.h[idx]), np.where(r2 < 1.0, 0.15, 0.0)
