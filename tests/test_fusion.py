"""Fusion over the descent (flight_sw.fusion): the hazard rule, resampling between cell sizes, bounds, sites."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from synthetic import frames_of

from flight_sw.fusion import (
    FusionParams,
    fuse,
    fused_state,
    overturn_margin,
    prior_logodds,
    resample,
    result_logodds,
    to_hazard_grid,
)
from flight_sw.mapping import HazardGrid
from flight_sw.sites import select_safe_sites
from protocol.pairdir import STATE_OUTSIDE, STATE_SAFE, STATE_UNKNOWN, STATE_UNSAFE


def grid_of(state: np.ndarray, psafe: np.ndarray, origin=(0.0, 0.0), cell=1.0, elevation=None) -> HazardGrid:
    state = np.asarray(state, np.uint8)
    ps = np.asarray(psafe, np.float32).copy()
    ps[state == STATE_OUTSIDE] = np.nan
    hz = np.where(state == STATE_SAFE, 0.05, 1.0).astype(np.float32)
    hz[state == STATE_OUTSIDE] = np.nan
    el = np.zeros(state.shape, np.float32) if elevation is None else np.asarray(elevation, np.float32)
    return HazardGrid(hz, el, origin, cell, state, ps)


def uniform(state: int, p: float, shape=(6, 6), **kw) -> HazardGrid:
    return grid_of(np.full(shape, state, np.uint8), np.full(shape, p, np.float32), **kw)


def _roof_descent(alts, seed):
    """``(camera, poses, images)``: nadir views of a roof-shaped terrain (tests/synthetic.py) at ``alts`` m, 128 px."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic import NADIR_R, Texture, camera_fov30, render, roof

    from protocol.pairdir import Pose

    cam = camera_fov30(128)
    poses = [Pose(np.array([0.0, 0.0, h]), NADIR_R) for h in alts]
    tex = Texture.random(130.0, 75.0 / cam.fx / 1.5, seed)
    return cam, poses, [render(cam, p, roof(18.0, -2.0), tex)[0] for p in poses]


CALIBRATED = FusionParams(p_min=0.97, prior_p=0.80134741462826)  # what params_for gives fast (checked below)


@pytest.mark.parametrize("prm, need_doc", [(FusionParams(), 3), (CALIBRATED, 4)])
def test_one_hazard_needs_the_documented_evidence_to_be_overturned(prm, need_doc):
    l0 = prior_logodds(prm)
    per_result = prm.l_max - l0  # the most one result can add beyond the prior (P >= 0.999, clipped)
    need = math.ceil(overturn_margin(prm) / per_result - 1e-9)
    assert need == need_doc  # the module doc's counts
    fm = fuse(None, uniform(STATE_UNSAFE, 0.0), prm)
    assert np.all(fused_state(fm, prm)[0] == STATE_UNSAFE)
    for k in range(1, need + 1):
        fm = fuse(fm, uniform(STATE_SAFE, 0.9999), prm)  # as confident as a result can be
        st, _ = fused_state(fm, prm)
        if k < need:
            assert np.all(st != STATE_SAFE), f"one hazard overturned by only {k} later results"
        else:
            assert np.all(st == STATE_SAFE)
    # a hazard seen twice needs more than that
    fm = fuse(fuse(None, uniform(STATE_UNSAFE, 0.0), prm), uniform(STATE_UNSAFE, 0.0), prm)
    for _ in range(need):
        fm = fuse(fm, uniform(STATE_SAFE, 0.9999), prm)
    assert np.all(fused_state(fm, prm)[0] != STATE_SAFE)
    assert math.ceil(overturn_margin(prm, 2) / per_result - 1e-9) > need


def test_fused_safe_cells_respect_the_rule_on_random_sequences():
    """Property: a fused-safe cell that results called hazardous n_u times got at least overturn_margin(n_u)
    of evidence for "safe" beyond the prior from the other results, whatever the order. Soft unsafe calls
    (P(safe) >= hard_unsafe_p) are evidence like any other; with every earlier result's evidence carried
    whole against "safe" (``weight_against = 1``) the bound holds for the net sum of the others' evidence."""
    rng = np.random.default_rng(7)
    params = (
        FusionParams(),
        CALIBRATED,
        FusionParams(weight=1.0, prior_p=0.7, p_accumulate=0.0),
        dataclasses.replace(CALIBRATED, weight_against=1.0),
        dataclasses.replace(CALIBRATED, hard_unsafe_p=1.0),
    )
    for prm in params:
        l0 = prior_logodds(prm)
        for trial in range(40):
            n = int(rng.integers(2, 8))
            shape = (9, 11)
            grids, logs = [], []
            for _ in range(n):
                st = rng.choice(
                    [STATE_SAFE, STATE_UNSAFE, STATE_UNKNOWN, STATE_OUTSIDE], size=shape, p=[0.55, 0.1, 0.25, 0.1]
                )
                ps = np.where(st == STATE_SAFE, rng.uniform(0.97, 1.0, shape), rng.uniform(0.0, 0.97, shape))
                ps = np.where(
                    st == STATE_UNSAFE, np.where(rng.random(shape) < 0.5, 0.0, rng.uniform(0, 0.5, shape)), ps
                )
                g = grid_of(st, ps)
                grids.append(g)
                logs.append(result_logodds(g, prm))
            fm = None
            levels = [str(rng.choice(["full", "coarse"])) for _ in grids]
            for g, lvl in zip(grids, levels):  # at random levels: a coarse result's rule must keep the bound as well
                fm = fuse(fm, g, prm, level=lvl)
            assert fm is not None
            st, _ = fused_state(fm, prm)
            L = np.stack(logs)  # NaN: the result did not map the cell
            calls = -prm.l_unsafe >= L  # the hazard calls
            assert np.array_equal(
                calls,
                (np.stack([g.state for g in grids]) == STATE_UNSAFE)
                & ~(np.stack([g.psafe for g in grids]) >= prm.hard_unsafe_p),
            )
            unsafe_calls = calls.sum(axis=0)
            e = np.where(calls, np.nan, L - l0)
            others = np.nansum(e if prm.weight_against == 1 else np.fmax(e, 0.0), axis=0)
            flagged = (st == STATE_SAFE) & (unsafe_calls > 0)
            for i, j in zip(*np.nonzero(flagged)):
                assert others[i, j] >= overturn_margin(prm, int(unsafe_calls[i, j])) - 1e-4, (trial, i, j)
            newest = np.full(shape, STATE_OUTSIDE, np.uint8)  # the newest full-level call with evidence
            for g, lg, lvl in zip(grids, logs, levels):
                newest = np.where(np.isfinite(lg), g.state if lvl == "full" else STATE_OUTSIDE, newest)
            assert np.all(st[newest == STATE_UNSAFE] == STATE_UNSAFE)  # a newest unsafe call is what the map says
            seen = np.any(np.stack([g.state for g in grids]) != STATE_OUTSIDE, axis=0)
            assert np.array_equal(st == STATE_OUTSIDE, ~seen)  # the unseen cells stay outside, the seen ones do not


def test_a_coarse_result_does_not_replace_what_a_full_one_measured():
    """Where a full-level result's evidence stands, a coarse one (a half-resolution DEM, 1 m errors) keeps the
    cell's evidence, call and elevation, and adds only its evidence against "safe"; elsewhere it enters whole."""
    prm = CALIBRATED
    full = grid_of(np.full((6, 6), STATE_SAFE), np.full((6, 6), 0.999), elevation=np.full((6, 6), 2.0))
    st = np.full((6, 8), STATE_UNKNOWN, np.uint8)  # 2 columns beyond the full result's extent
    st[0, 0] = STATE_UNSAFE  # and one cell it calls unsafe
    ps = np.where(st == STATE_UNSAFE, 0.0, 0.6)
    coarse = grid_of(st, ps, elevation=np.full((6, 8), 3.5))
    fm = fuse(fuse(None, full, prm), coarse, prm, level="coarse")
    state, psafe = fused_state(fm, prm)
    assert state[0, 0] == STATE_UNSAFE  # its hazard counts whole
    assert np.all(state[1:, :6] == STATE_SAFE) and np.all(fm.elevation[1:, :6] == 2.0)  # the full result stands
    assert np.all(state[:, 6:] == STATE_UNKNOWN) and np.all(fm.elevation[:, 6:] == 3.5)  # new ground: as it says
    # the same coarse result at the full level replaces the map: nothing is called safe any more
    fm = fuse(fuse(None, full, prm), coarse, prm, level="full")
    assert not (fused_state(fm, prm)[0] == STATE_SAFE).any() and np.all(fm.elevation == 3.5)
    with pytest.raises(ValueError, match="level"):
        fuse(None, full, prm, level="partial")
    # and a full-level result after the coarse one enters whole again
    fm = fuse(fuse(fuse(None, full, prm), coarse, prm, level="coarse"), coarse, prm, level="full")
    assert not (fused_state(fm, prm)[0] == STATE_SAFE).any()


def test_a_soft_unsafe_call_is_evidence_and_a_hazard_call_is_not_overturned_by_one_result():
    """An unsafe call whose own P(safe) only leans unsafe (no hazard cue, 0.3 here) is that much evidence: alone the
    map calls the cell unsafe, a newer result that measured it differently replaces the call, and one confident
    newer result can clear it. An unsafe call at P(safe) < hard_unsafe_p (a cue: 0 on pixels) is a hazard call."""
    prm = CALIBRATED
    alone = fused_state(fuse(None, uniform(STATE_UNSAFE, 0.3), prm), prm)[0]
    assert np.all(alone == STATE_UNSAFE)  # a map of one result is that result
    doubt = fuse(fuse(None, uniform(STATE_UNSAFE, 0.3), prm), uniform(STATE_UNKNOWN, 0.6), prm)
    assert np.all(fused_state(doubt, prm)[0] == STATE_UNKNOWN)
    cleared = fuse(fuse(None, uniform(STATE_UNSAFE, 0.3), prm), uniform(STATE_SAFE, 0.999), prm)
    assert np.all(fused_state(cleared, prm)[0] == STATE_SAFE)
    assert np.all(fused_state(fuse(cleared, uniform(STATE_UNSAFE, 0.3), prm), prm)[0] == STATE_UNSAFE)
    for p_hazard in (0.0, 0.04, float("nan")):  # a cue, a near-certain hazard, and no P(safe) at all
        fm = fuse(fuse(None, uniform(STATE_UNSAFE, p_hazard), prm), uniform(STATE_SAFE, 0.999), prm)
        assert not np.any(fused_state(fm, prm)[0] == STATE_SAFE), p_hazard
    # hard_unsafe_p = 1: every unsafe call is a hazard call (the rule before 2026-12-03)
    old = dataclasses.replace(prm, hard_unsafe_p=1.0, weight_against=1.0)
    fm = fuse(fuse(None, uniform(STATE_UNSAFE, 0.3), old), uniform(STATE_SAFE, 0.999), old)
    assert not np.any(fused_state(fm, old)[0] == STATE_SAFE)


def test_an_unsafe_call_survives_a_move_to_a_coarser_grid():
    """Moved onto a coarser grid, a cell holds the unsafe call and the hazard calls of any of its finer parts
    (the maximum), as its log-odds takes their minimum: a soft call in one fine cell keeps its coarse cell unsafe."""
    prm = CALIBRATED
    st = np.full((8, 8), STATE_SAFE, np.uint8)
    st[2, 4] = STATE_UNSAFE  # centre (4, -2): the coarse cell [1, 2]
    fine = grid_of(st, np.where(st == STATE_UNSAFE, 0.3, 0.999), cell=1.0)
    no_evidence = grid_of(
        np.full((4, 4), STATE_UNKNOWN), np.full((4, 4), 0.5), cell=2.0, elevation=np.full((4, 4), np.nan)
    )
    fm = fuse(fuse(None, fine, prm), no_evidence, prm)
    assert fm.cell_m == 2.0 and fm.vetoed is not None
    state = fused_state(fm, prm)[0]
    assert state[1, 2] == STATE_UNSAFE and np.count_nonzero(state == STATE_UNSAFE) == 1
    assert np.count_nonzero(state == STATE_SAFE) == 15
    hazard = grid_of(st, np.where(st == STATE_UNSAFE, 0.0, 0.999), cell=1.0)
    fm = fuse(fuse(None, hazard, prm), no_evidence, prm)
    assert fm.hazards is not None and fm.hazards[1, 2] == 1 and np.count_nonzero(fm.hazards) == 1


def test_gap_fills_are_reported_where_nothing_matched_and_are_no_evidence():
    """A result's gap fills (``HazardGrid.dem`` where it has no match) are what the fused map reports where no
    result matched the cell, the newest fill first; a match, older or newer, beats them. They add no evidence."""
    prm = CALIBRATED
    elev = np.full((6, 6), 2.0, np.float32)
    elev[:, :2] = np.nan  # no match in the first two columns ...
    dem = np.where(np.isfinite(elev), elev, np.float32(5.0))  # ... where the DEM filled 5 m
    st = np.full((6, 6), STATE_UNKNOWN, np.uint8)
    first = replace_dem(grid_of(st, np.full((6, 6), 0.999), elevation=elev), dem)
    fm = fuse(None, first, prm)
    g = to_hazard_grid(fm, prm)
    assert np.all(g.reported_elevation[:, :2] == 5.0) and np.all(g.reported_elevation[:, 2:] == 2.0)
    assert np.isnan(g.elevation[:, :2]).all()  # the sites read matches only
    assert np.all(fm.logodds[:, :2] == np.float32(prior_logodds(prm)))  # the prior: no evidence
    # a newer fill replaces the older one; a newer result's fill never replaces an older match
    second = replace_dem(grid_of(st, np.full((6, 6), 0.5), elevation=np.full((6, 6), np.nan)), np.full((6, 6), 7.0))
    g = to_hazard_grid(fuse(fm, second, prm), prm)
    assert np.all(g.reported_elevation[:, :2] == 7.0) and np.all(g.reported_elevation[:, 2:] == 2.0)
    # and a result without fills leaves the map's fills as they were
    assert (
        to_hazard_grid(fuse(fm, uniform(STATE_UNKNOWN, 0.5, elevation=np.full((6, 6), np.nan)), prm), prm).dem
        is not None
    )
    assert to_hazard_grid(fuse(None, uniform(STATE_SAFE, 0.999), prm), prm).dem is None
    with pytest.raises(ValueError, match="dem shape"):  # a reported DEM that is not the grid's is refused
        replace_dem(first, np.zeros((5, 6)))


def replace_dem(g: HazardGrid, dem: np.ndarray) -> HazardGrid:
    return dataclasses.replace(g, dem=np.asarray(dem, np.float32))


def test_newest_result_wins_would_fail_the_rule():
    """The rule test is able to fail: a 'newest result replaces the map' fusion breaks it at once."""
    prm = FusionParams()
    fm = fuse(None, uniform(STATE_UNSAFE, 0.0), prm)
    fm = fuse(fm, uniform(STATE_SAFE, 0.999), prm)
    assert np.all(fused_state(fm, prm)[0] != STATE_SAFE)  # fused: the hazard holds
    newest_only = fuse(None, uniform(STATE_SAFE, 0.999), prm)
    assert np.all(fused_state(newest_only, prm)[0] == STATE_SAFE)  # what 'newest wins' would report


def test_resampling_is_conservative_both_ways():
    # coarse (2 m) result with one unsafe cell -> onto a fine (0.5 m) map: all four by four children unsafe
    st = np.full((4, 4), STATE_SAFE, np.uint8)
    st[1, 2] = STATE_UNSAFE
    coarse = grid_of(st, np.where(st == STATE_SAFE, 0.99, 0.0), origin=(0.0, 0.0), cell=2.0)
    # fine cell centres never fall on a coarse cell's edge: the newest (fine) grid is the map's grid
    fine = uniform(STATE_SAFE, 0.99, shape=(14, 14), origin=(-0.25, 0.25), cell=0.5)
    prm = FusionParams()
    fm = fuse(fuse(None, coarse, prm), fine, prm)
    assert fm.cell_m == pytest.approx(0.5)
    s, _ = fused_state(fm, prm)
    X = fm.origin_xy[0] + np.arange(fm.shape[1]) * fm.cell_m
    Y = fm.origin_xy[1] - np.arange(fm.shape[0]) * fm.cell_m
    inside = (np.abs(X[None, :] - 4.0) < 1.0) & (np.abs(Y[:, None] + 2.0) < 1.0)  # the unsafe coarse cell
    assert inside.sum() == 16 and np.all(s[inside] != STATE_SAFE)
    assert np.all(s[~inside & (s != STATE_OUTSIDE)] == STATE_SAFE)
    # the union extent at the finer cell holds both grids
    fu = fuse(fuse(None, coarse, FusionParams(extent="union")), fine, FusionParams(extent="union"))
    assert fu.cell_m == pytest.approx(0.5) and fu.shape[0] * fu.cell_m >= 7.0
    # fine -> coarse: one unsafe fine cell makes its coarse cell the minimum
    v = np.full((8, 8), 3.0, np.float32)
    v[5, 5] = -9.0  # centre (2.5, -2.5): in coarse cell [1, 1] (centre (2, -2))
    out = resample(v, (0.0, 0.0), 0.5, (0.0, 0.0), 2.0, (2, 2))
    assert out[1, 1] == -9.0 and out[0, 0] == 3.0 and out[0, 1] == 3.0
    assert np.isnan(resample(v, (100.0, 0.0), 0.5, (0.0, 0.0), 2.0, (2, 2))).all()  # no overlap: no value


def _resample_by_definition(v, origin, cell, dst_origin, dst_cell, dst_shape, fill, pool_min, pool_max=False):
    """``resample`` as its doc defines it, one destination cell at a time (small grids only)."""
    out = np.full(dst_shape, np.float32(fill), np.float32)
    h, w = v.shape
    for r in range(dst_shape[0]):
        for c in range(dst_shape[1]):
            i = round((origin[1] - (dst_origin[1] - r * dst_cell)) / cell)
            j = round(((dst_origin[0] + c * dst_cell) - origin[0]) / cell)
            if 0 <= i < h and 0 <= j < w:
                out[r, c] = v[i, j]
    if (pool_min or pool_max) and cell < dst_cell * (1 - 1e-9):
        for i in range(h):
            for j in range(w):
                r = round((dst_origin[1] - (origin[1] - i * cell)) / dst_cell)
                c = round(((origin[0] + j * cell) - dst_origin[0]) / dst_cell)
                if 0 <= r < dst_shape[0] and 0 <= c < dst_shape[1] and np.isfinite(v[i, j]):
                    out[r, c] = (np.fmax if pool_max else np.fmin)(out[r, c], v[i, j])
    return out


@pytest.mark.parametrize("seed", range(40))
def test_resampling_matches_its_definition_cell_by_cell(seed):
    """The separable resampling (row block x column block minimum) equals the per-cell definition, for finer,
    coarser, same and shifted grids, with holes and without overlap."""
    rng = np.random.default_rng(seed)
    h, w = (int(x) for x in rng.integers(0, 14, 2))
    v = rng.normal(size=(h, w)).astype(np.float32)
    v[rng.random((h, w)) < 0.25] = np.nan
    cell = float(rng.choice([0.25, 0.5, 0.7, 1.0]))
    dst_cell = float(rng.choice([0.25, 0.5, 1.0, 1.3, 2.0, cell]))
    origin = (float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)))
    dst_origin = origin if seed % 5 == 0 else (float(rng.uniform(-4, 4)), float(rng.uniform(-4, 4)))
    dst_shape = (int(rng.integers(0, 16)), int(rng.integers(0, 16)))
    for fill in (np.nan, 0.0):
        for pool_min, pool_max in ((True, False), (False, False), (False, True)):
            got = resample(v, origin, cell, dst_origin, dst_cell, dst_shape, fill, pool_min, pool_max)
            want = _resample_by_definition(v, origin, cell, dst_origin, dst_cell, dst_shape, fill, pool_min, pool_max)
            assert np.array_equal(got, want, equal_nan=True)


def test_map_follows_the_newest_grid_and_is_bounded():
    prm = FusionParams()  # extent = newest
    a = uniform(STATE_UNSAFE, 0.0, shape=(10, 10), origin=(0.0, 0.0), cell=1.0)
    b = uniform(STATE_SAFE, 0.999, shape=(10, 10), origin=(5.0, 0.0), cell=1.0)  # half overlaps a
    fm = fuse(fuse(None, a, prm), b, prm)
    assert fm.shape == (10, 10) and fm.origin_xy == (5.0, 0.0)
    s, _ = fused_state(fm, prm)
    assert np.all(s[:, :5] != STATE_SAFE) and np.all(s[:, 5:] == STATE_SAFE)  # a's hazard kept where a saw it
    big = uniform(STATE_SAFE, 0.99, shape=(300, 300), cell=0.1)
    fm = fuse(None, big, FusionParams(max_cells=10_000))
    assert fm.logodds.size <= 10_000 and fm.cell_m > 0.1
    with pytest.raises(ValueError, match="extent"):
        fuse(None, a, FusionParams(extent="all"))


def test_sites_on_the_fused_map_and_unknown_adds_nothing():
    prm = FusionParams()
    st = np.full((40, 40), STATE_SAFE, np.uint8)
    st[:, :8] = STATE_UNSAFE
    g = grid_of(st, np.where(st == STATE_SAFE, 0.99, 0.0), origin=(-20.0, 20.0), cell=1.0)
    fm = fuse(None, g, prm)
    blind = uniform(
        STATE_UNKNOWN, 0.8, shape=(40, 40), origin=(-20.0, 20.0), cell=1.0, elevation=np.full((40, 40), np.nan)
    )
    fm = fuse(fm, blind, prm)
    hg = to_hazard_grid(fm, prm)
    assert np.array_equal(hg.state, fused_state(fuse(None, g, prm), prm)[0])  # an image-only result changes nothing
    assert np.all(hg.hazard[hg.state == STATE_UNSAFE] == 1.0) and np.all(hg.hazard[hg.state == STATE_SAFE] < 1.0)
    sites, reason = select_safe_sites(hg, 3.0, (0.0, 0.0), 3, 0.5)
    assert sites and reason == ""
    for s in sites:
        assert s.x > -20.0 + 8 + 1.5  # clear of the unsafe strip


def test_a_result_with_no_elevation_and_no_psafe_leaves_the_map_as_it_was():
    """An image-only result (a degraded level) may carry no P(safe) at all: it must not wipe earlier evidence."""
    for prm in (FusionParams(), CALIBRATED):
        fm = fuse(None, uniform(STATE_SAFE, 0.999), prm)
        blind = uniform(STATE_UNKNOWN, np.nan, elevation=np.full((6, 6), np.nan))
        fm2 = fuse(fm, blind, prm)
        assert np.array_equal(fm2.logodds, fm.logodds) and np.all(fused_state(fm2, prm)[0] == STATE_SAFE)


def test_results_without_an_elevation_never_make_ground_safe():
    """An image-only result (no DEM) may carry a high context-prior P(safe) on unknown cells; summed over
    the descent that must not call unmeasured ground safe (the demo showed FP 10 % before this rule)."""
    prm = FusionParams()
    blind = uniform(STATE_UNKNOWN, 0.96, elevation=np.full((6, 6), np.nan))
    fm = None
    for _ in range(5):
        fm = fuse(fm, blind, prm)
    assert fm is not None and not (fused_state(fm, prm)[0] == STATE_SAFE).any()
    fm = fuse(fm, uniform(STATE_UNKNOWN, 0.85), prm)  # then one measured, below p_min: the blind ones added nothing
    assert not (fused_state(fm, prm)[0] == STATE_SAFE).any()


def test_an_image_only_result_neither_clears_nor_condemns_what_later_pairs_measure():
    """A slow processor's first pairs come back image-only: no elevation, the trees' context P(safe) (0.09
    on a snapdragon801 approach) on every cell, and dark shadow called unsafe. Taken against "safe",
    that left the full-level pairs below it almost nothing safe (docs/hil.md, stop 32). Only the
    shadow call may count; a later measured result then decides alone."""
    shape = (12, 12)
    blind_st = np.full(shape, STATE_UNKNOWN, np.uint8)
    blind_st[:, :3] = STATE_UNSAFE  # a shadow: P(safe) 0, a hard cue
    blind = grid_of(blind_st, np.where(blind_st == STATE_UNSAFE, 0.0, 0.09), elevation=np.full(shape, np.nan))
    measured = uniform(STATE_SAFE, 0.98, shape=shape)  # a full-level pair, safe at its own P floor
    for prm in (FusionParams(), CALIBRATED):
        fm = fuse(fuse(None, blind, prm), measured, prm)
        st, _ = fused_state(fm, prm)
        assert np.all(st[:, 3:] == STATE_SAFE), "the image-only prior was taken as evidence against safety"
        assert np.all(st[:, :3] == STATE_UNSAFE), "the shadow it called unsafe was lost"
        alone = fused_state(fuse(None, measured, prm), prm)[0]
        assert np.array_equal(st[:, 3:], alone[:, 3:])
    # the same prior with an elevation is a measurement: against "safe" it still counts
    fm = fuse(fuse(None, uniform(STATE_UNKNOWN, 0.09, shape=shape), CALIBRATED), measured, CALIBRATED)
    assert not (fused_state(fm, CALIBRATED)[0] == STATE_SAFE).any()


def test_a_calibrated_prior_is_counted_once():
    """Calibrated P(safe) is a posterior holding the prior share of safe ground; results that add no
    evidence beyond it must leave a cell at the prior, not add it up into "safe"."""
    prior = 0.8
    plain = FusionParams(prior_p=0.5, weight=1.0, accumulate_calls=0)  # no call needed: the prior rule alone
    counted_once = FusionParams(prior_p=prior, weight=1.0, accumulate_calls=0)
    vague = uniform(STATE_UNKNOWN, prior)
    fm_plain = fm_once = None
    for _ in range(4):
        fm_plain, fm_once = fuse(fm_plain, vague, plain), fuse(fm_once, vague, counted_once)
    assert fm_plain is not None and fm_once is not None
    assert np.all(fused_state(fm_plain, plain)[0] == STATE_SAFE)  # four "80 %" results read as 99.6 %
    st, ps = fused_state(fm_once, counted_once)
    assert np.all(st == STATE_UNKNOWN) and np.allclose(ps, prior, atol=1e-5)
    # evidence beyond the prior still adds up: two results at 0.94 with a 0.8 prior pass p_min = 0.95
    sure = FusionParams(p_min=0.95, prior_p=prior, weight=1.0, p_accumulate=0.0, accumulate_calls=0)
    fm = fuse(fuse(None, uniform(STATE_UNKNOWN, 0.94), sure), uniform(STATE_UNKNOWN, 0.94), sure)
    assert np.all(fused_state(fm, sure)[0] == STATE_SAFE)


def test_the_newest_result_enters_whole():
    """A finer, newer result that doubts a cell outweighs an earlier confident call (the stream failure:
    coarse high results carried safe calls onto hazards the low results saw)."""
    prm = CALIBRATED
    fm = fuse(None, uniform(STATE_SAFE, 0.999), prm)
    fm = fuse(fm, uniform(STATE_UNKNOWN, 0.9), prm)
    st, ps = fused_state(fm, prm)
    assert np.all(st == STATE_UNKNOWN) and np.all(ps < prm.p_accumulate)  # not called by the newest: the bar
    # and evidence from the past is discounted: for "safe" by w, against it by weight_against; a hazard call not at all
    l0 = prior_logodds(prm)
    e_safe = math.log(0.999 / 0.001) - l0
    fm = fuse(fuse(None, uniform(STATE_SAFE, 0.999), prm), uniform(STATE_UNKNOWN, 0.5), prm)
    assert np.allclose(fm.logodds, prm.weight * e_safe, atol=1e-4)
    for first in (uniform(STATE_UNKNOWN, 0.01), uniform(STATE_UNSAFE, 0.2)):  # doubt, and a soft unsafe call
        e_doubt = math.log(0.01 / 0.99 if first.state[0, 0] == STATE_UNKNOWN else 0.2 / 0.8) - l0
        fm = fuse(fuse(None, first, prm), uniform(STATE_UNKNOWN, 0.5), prm)
        assert np.allclose(fm.logodds, prm.weight_against * e_doubt, atol=1e-4)
        whole = dataclasses.replace(prm, weight_against=1.0)
        fm = fuse(fuse(None, first, whole), uniform(STATE_UNKNOWN, 0.5), whole)
        assert np.allclose(fm.logodds, e_doubt, atol=1e-4)
    fm = fuse(fuse(None, uniform(STATE_UNSAFE, 0.0), prm), uniform(STATE_UNKNOWN, 0.5), prm)
    assert np.allclose(fm.logodds, -prm.l_unsafe - l0, atol=1e-4)
    fm = fuse(fm, uniform(STATE_SAFE, 0.999), prm)  # still whole after later evidence for "safe"
    assert np.allclose(fm.logodds, math.log(999.0) - prm.l_unsafe - 2 * l0, atol=1e-3)


def test_accumulated_evidence_needs_the_higher_bar():
    """A cell the newest measuring result did not call safe becomes safe only at p_accumulate; results
    that each say "96 % safe" must not add up to safe below that bar."""
    prm = CALIBRATED
    fm = None
    for _ in range(5):
        fm = fuse(fm, uniform(STATE_UNKNOWN, 0.96), prm)
    assert fm is not None
    st, ps = fused_state(fm, prm)
    assert np.all(ps >= 0.97) and np.all(ps < 0.995)  # over p_min, under the bar
    assert np.all(st == STATE_UNKNOWN)
    free = dataclasses.replace(prm, p_accumulate=0.0, accumulate_calls=0)  # without the bars: safe
    assert np.all(fused_state(fm, free)[0] == STATE_SAFE)
    called = fuse(fm, uniform(STATE_SAFE, 0.98), prm)  # a result that calls it safe itself needs p_min
    assert np.all(fused_state(called, prm)[0] == STATE_SAFE)
    # the call survives resampling onto a finer grid; onto a coarser one only if all its parts were called
    st2 = np.full((6, 6), STATE_UNKNOWN, np.uint8)
    st2[:, :3] = STATE_SAFE
    half = fuse(None, grid_of(st2, np.where(st2 == STATE_SAFE, 0.98, 0.9)), prm)
    blind = uniform(
        STATE_UNKNOWN, 0.9, shape=(12, 12), origin=(-0.25, 0.25), cell=0.5, elevation=np.full((12, 12), np.nan)
    )
    fine = fuse(half, blind, prm)
    assert fine.called[:, :4].min() == 1 and fine.called[:, 8:].max() == 0


def test_summed_evidence_never_calls_safe_what_no_result_called_safe():
    """The accumulated route needs a call (module doc): results that were each sure enough but held the cell
    back (their FP budget, slope cap) do not add up to "safe"; once one of them called it, the sum may."""
    prm = CALIBRATED
    assert prm.accumulate_calls == 1
    fm = None
    for _ in range(4):
        fm = fuse(fm, uniform(STATE_UNKNOWN, 0.99), prm)  # over p_min, never called
    assert fm is not None
    st, ps = fused_state(fm, prm)
    assert np.all(ps >= prm.p_accumulate) and np.all(fm.calls == 0)
    assert np.all(st == STATE_UNKNOWN)
    assert np.all(fused_state(fm, dataclasses.replace(prm, accumulate_calls=0))[0] == STATE_SAFE)  # the old rule
    # one earlier call and the same summed evidence: safe, though the newest result did not call it
    st1 = np.full((6, 6), STATE_UNKNOWN, np.uint8)
    st1[:, :3] = STATE_SAFE
    fm = fuse(None, grid_of(st1, np.full((6, 6), 0.99)), prm)
    for _ in range(3):
        fm = fuse(fm, uniform(STATE_UNKNOWN, 0.99), prm)
    st, _ = fused_state(fm, prm)
    assert np.all(fm.calls[:, :3] == 1) and np.all(fm.calls[:, 3:] == 0) and np.all(fm.called == 0)
    assert np.all(st[:, :3] == STATE_SAFE) and np.all(st[:, 3:] == STATE_UNKNOWN)
    # a coarser map cell counts the calls of its least-called part: columns 0-1 called, 2-3 half, 4-5 none
    coarse = fuse(fm, uniform(STATE_UNKNOWN, 0.99, shape=(3, 3), origin=(0.5, -0.5), cell=2.0), prm)
    assert np.array_equal(coarse.calls, np.array([[1, 0, 0]] * 3, np.uint8))
    with pytest.raises(ValueError, match="accumulate_calls"):
        dataclasses.replace(prm, accumulate_calls=-1).validate()


def test_params_for_follow_the_pipeline_that_made_the_result():
    from flight_sw.fusion import params_for
    from flight_sw.pipeline import PRESETS
    from flight_sw.psafe import load_model

    fast = dataclasses.asdict(PRESETS["fast"])
    prm = params_for(fast, {}, FusionParams())
    prm.validate()
    assert prm.p_min == fast["psafe_min"] and prm.p_accumulate > prm.p_min
    assert prm.prior_p == load_model().info["safe_share"] and 0.5 < prm.prior_p < 1
    # the prior of the model that called the result (one per image size), as the result records it
    assert params_for(fast, {"psafe_safe_share": 0.7}, FusionParams()).prior_p == 0.7
    fallback = params_for(fast, {"psafe_fallback": "not fitted for 128x128"}, FusionParams())
    assert fallback == dataclasses.replace(FusionParams(), p_min=fast["psafe_min"])  # the Gaussian's flat prior
    thesis = params_for(dataclasses.asdict(PRESETS["thesis"]), {}, FusionParams())
    assert thesis.prior_p == 0.5 and thesis.p_min == PRESETS["thesis"].psafe_min
    assert dataclasses.replace(prm, extent="newest") == CALIBRATED  # the settings the tests above use


class _Link:
    """Collects what the flight process sends."""

    def __init__(self) -> None:
        self.sent: list = []

    def send(self, msg) -> None:
        from protocol.codec import Encoded, encode_message

        if isinstance(msg, Encoded):  # sent with the body it was measured on: that body must be the message's
            assert msg.body == encode_message(msg.message)
            msg = msg.message
        self.sent.append(msg)

    def flush(self, timeout: float | None = None) -> bool:  # everything is handed over at once
        return True

    def stats(self) -> dict:
        return {"bytes_sent": 0}


@pytest.mark.slow
def test_flight_process_reports_the_fused_map(monkeypatch):
    """Two pairs of a descent: the second Result is the fused map (the first pair's hazards kept), not the pair."""
    from flight_sw.flight_main import FaultPlan, FlightProcess
    from flight_sw.pipeline import run_pipeline
    from protocol.grids import psafe_from_wire
    from protocol.messages import Config, Result, Telemetry

    alts = (200.0, 100.0, 150.0, 75.0)
    cam, poses, imgs = _roof_descent(alts, seed=21)
    results = {}
    for fusion in (1, 0):
        link = _Link()
        fp = FlightProcess(link, FaultPlan())
        fp.handle(
            Config(camera=cam.to_dict(), budget="host", deadline_s=30.0, preset="fast", options={"fusion": fusion})
        )
        for i, (a, b) in enumerate(((0, 1), (2, 3))):
            for f in frames_of(f"p{i}", 10 * i, [(poses[a], imgs[a]), (poses[b], imgs[b])]):
                fp.handle(f)
        res = [m for m in link.sent if isinstance(m, Result)]
        tel = [m for m in link.sent if isinstance(m, Telemetry)]
        assert len(res) == 2 and len(tel) == 2, [type(m).__name__ for m in link.sent]
        results[fusion] = (res, tel)
    (fused1, fused2), tel = results[1]
    (alone1, alone2), _ = results[0]
    # first pair: fusing into an empty map gives the pair's own states back
    assert np.array_equal(fused1.state_grid, alone1.state_grid)
    # second pair: the map is on the second pair's grid, and it differs from that pair alone
    assert fused2.state_grid.shape == alone2.state_grid.shape and fused2.grid_origin_xy == alone2.grid_origin_xy
    assert not np.array_equal(fused2.state_grid, alone2.state_grid)
    assert "fusion" in tel[1].stages
    # every cell the first pair called unsafe that the second maps is not safe in the fused map (one result
    # cannot overturn a hazard, module doc)
    g1 = run_pipeline(imgs[0], imgs[1], poses[0], poses[1], cam).grid
    g2 = alone2
    i2, j2 = np.mgrid[0 : g2.state_grid.shape[0], 0 : g2.state_grid.shape[1]]
    X = g2.grid_origin_xy[0] + j2 * g2.grid_cell_m
    Y = g2.grid_origin_xy[1] - i2 * g2.grid_cell_m
    j1 = np.rint((X - g1.origin_xy[0]) / g1.cell_m).astype(int)
    i1 = np.rint((g1.origin_xy[1] - Y) / g1.cell_m).astype(int)
    on = (i1 >= 0) & (i1 < g1.state.shape[0]) & (j1 >= 0) & (j1 < g1.state.shape[1])
    was_unsafe = np.zeros(on.shape, bool)
    was_unsafe[on] = g1.state[i1[on], j1[on]] == STATE_UNSAFE
    assert was_unsafe.sum() > 50
    assert not np.any(fused2.state_grid[was_unsafe] == STATE_SAFE)
    p = psafe_from_wire(fused2.psafe_grid)
    assert np.all(p[fused2.state_grid == STATE_SAFE] >= 0.9 - 1 / 254)
    for s in fused2.sites:  # sites stand on the fused map's known-safe ground
        i = int(round((fused2.grid_origin_xy[1] - s.y) / fused2.grid_cell_m))
        j = int(round((s.x - fused2.grid_origin_xy[0]) / fused2.grid_cell_m))
        assert fused2.state_grid[i, j] == STATE_SAFE


def test_flight_process_applies_the_relief_guard_to_the_fused_map():
    """The fused map's sites follow the preset's relief guard, as the single-pair pipeline's do."""
    import sys
    from pathlib import Path
    from types import SimpleNamespace

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic import flattened_wall_grid

    from flight_sw.flight_main import FaultPlan, FlightProcess
    from flight_sw.pipeline import PRESETS

    # everything measured safe: a plateau, a 20 m wall the DEM flattened into a ramp, a floor
    grid = flattened_wall_grid((-38.0, 40.0))
    params = dataclasses.asdict(PRESETS["fast"]) | {"psafe_model": "gaussian"}
    near_wall = []
    for relief in (0.0, PRESETS["fast"].site_relief_max_m):
        fp = FlightProcess(_Link(), FaultPlan())
        res = SimpleNamespace(params=params | {"site_relief_max_m": relief}, info={}, grid=grid, level="full")
        _, sites, reason = fp._fuse(res)
        assert sites and reason is None
        # the wall's top is at x = 0 (column 76); every site's 30 m square must stay clear of it
        near_wall.append(min(abs(s.x) for s in sites))
    assert near_wall[0] < 2.0  # the aim point (0, 0) is at the wall: without the guard the site is there
    assert near_wall[1] >= 14.0
    # a pair whose footprint is below the model's scale calls nothing safe: the fused map's "no site" says why, as
    # `process` does (the HIL's said only "no cell is known safe"; sites QA of stop 75)
    from flight_sw.mapping import HazardGrid
    from protocol.pairdir import STATE_UNKNOWN

    n = 40
    blank = HazardGrid(np.ones((n, n), np.float32), np.zeros((n, n), np.float32), (0.0, 0.0), 4.0,
                       np.full((n, n), STATE_UNKNOWN, np.uint8), np.full((n, n), 0.5, np.float32))  # fmt: skip
    why = "the 3 m footprint is 0.29 px here, below the 0.39 px the P(safe) model was fitted down to"
    res = SimpleNamespace(params=params, info={"psafe_beyond_scale": why}, grid=blank, level="full")
    _, sites, reason = FlightProcess(_Link(), FaultPlan())._fuse(res)
    assert not sites and reason is not None and reason.startswith(why + " (no cell is known safe"), reason
    # a pair whose own search gave way to the deadline: the reason says the fused map's search ran, as a row that
    # listed "sites" among the skipped stages beside a reason about the map read as a contradiction (QA of stop 84)
    res = SimpleNamespace(params=params, info={"skipped": ["full_dem", "sites"]}, grid=blank, level="coarse")
    _, sites, reason = FlightProcess(_Link(), FaultPlan())._fuse(res)
    assert not sites and reason is not None and reason.startswith("no cell is known safe"), reason
    assert reason.endswith("on the descent's fused map (this pair's own site search was skipped for the deadline)")


def test_a_pair_whose_sites_are_withheld_is_not_fused_into_the_descents_map():
    """A pair whose altimeter or images contradict its poses offers no site; its map had still been folded into the
    descent's, where every later pair's sites were chosen (stop 60's review). It is now left out of the fused map,
    and its Result reports the map fused so far with no site."""
    import sys
    from pathlib import Path
    from types import SimpleNamespace

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic import flattened_wall_grid

    from flight_sw.flight_main import FaultPlan, FlightProcess
    from flight_sw.pipeline import PRESETS

    grid = flattened_wall_grid((-38.0, 40.0))
    params = dataclasses.asdict(PRESETS["fast"]) | {"psafe_model": "gaussian"}
    fp = FlightProcess(_Link(), FaultPlan())
    why = "no site is offered on this map: it rests on frame 1, whose navigation pose the images contradict"
    bad = SimpleNamespace(params=params, info={"sites_withheld": why}, grid=grid, level="full")
    g0, sites, reason = fp._fuse(bad)  # first pair: nothing fused yet, its own map reported, no site
    assert fp.fused is None and g0 is grid and sites == [] and reason == why
    good = SimpleNamespace(params=params, info={}, grid=grid, level="full")
    g1, sites, _ = fp._fuse(good)
    assert sites and fp.fused is not None and fp.fused.results == 1
    before = fp.fused.logodds.copy()
    unsafe = dataclasses.replace(grid, state=np.full_like(grid.state, STATE_UNSAFE))
    g2, sites, reason = fp._fuse(
        SimpleNamespace(params=params, info={"sites_withheld": why}, grid=unsafe, level="full")
    )
    assert sites == [] and reason == why
    assert fp.fused.results == 1 and np.array_equal(fp.fused.logodds, before)  # the pair left no trace
    assert np.array_equal(g2.state, g1.state) and np.any(g2.state == STATE_SAFE)  # the map fused so far


def test_the_result_carries_the_maps_states_code_for_code():
    """The Result's state grid is the fused map's, code for code: an unsafe cell goes out as 1, unknown as 2,
    outside as 255, through the encoder too. The HIL runs only check that the codes are among {0, 1, 2, 255}; a
    Result that sent every unsafe cell as unknown passed them (mutation audit of stop 75)."""
    from types import SimpleNamespace

    from flight_sw.flight_main import FlightProcess
    from protocol.codec import decode_message, encode_message
    from protocol.messages import Config, Result

    codes = np.array([STATE_SAFE, STATE_UNSAFE, STATE_UNKNOWN, STATE_OUTSIDE], np.uint8)
    state = codes[(np.arange(6 * 8).reshape(6, 8) * 7 // 3) % 4]
    assert set(np.unique(state)) == set(codes)
    grid = grid_of(state, np.where(state == STATE_SAFE, 0.95, 0.3), origin=(-3.0, 4.0), cell=0.5)
    res = SimpleNamespace(degraded=False, level="full", info={}, hazard=None, elevation=None, state=None, filled=None)
    cam = {"width": 128, "height": 128, "fx": 238.9, "fy": 238.9, "cx": 63.5, "cy": 63.5}
    cfg = Config(camera=cam, budget="host", deadline_s=30.0, preset="fast", options={})
    msg = FlightProcess._result_message(res, (1, 2), cfg, grid, [], None)
    assert msg.state_grid.dtype == np.uint8 and np.array_equal(msg.state_grid, state)
    back = decode_message(encode_message(msg))
    assert isinstance(back, Result) and np.array_equal(back.state_grid, state)
    assert (back.state_grid == STATE_UNSAFE).sum() == (state == STATE_UNSAFE).sum() > 0


def test_flight_process_plans_each_pair_from_what_the_last_ones_reserved_work_cost(monkeypatch):
    """The first pair of a Config plans its reserves from the nominal slowdown; each later one from the
    largest measured cost of the reserved work on the last pairs (anytime.measured_reserve_ratio); a new
    Config measures anew."""
    import flight_sw.flight_main as fm
    from protocol.messages import Config, Result

    cam, poses, imgs = _roof_descent((200.0, 100.0), seed=22)
    seen: list = []
    real = fm.run_pipeline

    def spy(*args, **kw):
        seen.append((kw.get("reserve_measured"), list(fp.reserve_ratios)))  # what it was told, what it had
        return real(*args, **kw)

    monkeypatch.setattr(fm, "run_pipeline", spy)
    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    cfg = {"camera": cam.to_dict(), "budget": "host", "deadline_s": 30.0, "preset": "fast"}
    fp.handle(Config(**cfg, options={"time_scale": 2.0}))
    for i in range(fm.RESERVE_HISTORY + 1):
        for f in frames_of(f"p{i}", 10 * i, list(zip(poses, imgs))):
            fp.handle(f)
    assert len([m for m in link.sent if isinstance(m, Result)]) == fm.RESERVE_HISTORY + 1
    assert seen[0] == (None, [])
    for k, (told, had) in enumerate(seen[1:], 1):
        assert len(had) == min(k, fm.RESERVE_HISTORY)  # the last few pairs only
        assert all(v > 0 for v in had) and told == max(had)  # planned from the largest of them
    fp.handle(Config(**cfg, options={"time_scale": 4.0}))
    for f in frames_of("q", 100, list(zip(poses, imgs))):
        fp.handle(f)
    assert seen[-1] == (None, [])


def test_the_next_results_line_time_follows_the_last_few_results():
    """The line time planned for the next Result: RESULT_MARGIN x the largest of the last RESULT_HISTORY Results, never
    under half the camera prior; an early large Result (an approach's high, oblique fused map) stops counting."""
    import flight_sw.flight_main as fm
    from protocol.messages import Config

    cam = {"width": 512, "height": 512, "fx": 955.0, "fy": 955.0, "cx": 255.5, "cy": 255.5}
    cfg = Config(camera=cam, budget="host", deadline_s=2.0, preset="fast", options={"link_baud": 921600})
    fp = fm.FlightProcess(_Link(), fm.FaultPlan())
    fp.handle(cfg)
    prior = fp.expected_result_bytes(cfg)
    assert prior == fp._prior_result_bytes(cfg) > 0
    for size in (150_000, 5_000, 6_000):
        fp.note_result_bytes(size)
    assert fp.expected_result_bytes(cfg) == pytest.approx(fm.RESULT_MARGIN * 150_000)  # still among the last three
    fp.note_result_bytes(25_000)
    assert fp.expected_result_bytes(cfg) == pytest.approx(max(fm.RESULT_MARGIN * 25_000, fm.PRIOR_FLOOR * prior))
    for _ in range(fm.RESULT_HISTORY):
        fp.note_result_bytes(1_000)
    assert fp.expected_result_bytes(cfg) == pytest.approx(fm.PRIOR_FLOOR * prior)  # the floor
    fp.handle(Config(camera=cam, budget="host", deadline_s=3.0, preset="fast", options={"link_baud": 921600}))
    assert fp.result_bytes == [] and fp.expected_result_bytes(cfg) == prior  # a new Config starts again


def test_the_flight_sends_elevations_in_the_configs_unit_and_refuses_a_bad_one():
    """``elevation_unit_cm`` u: the Result says u, its elevations decode within u/2 of the 1 cm ones, the first
    Result's planned size shrinks with it, and an out-of-range u is a ``bad_config`` Error."""
    import flight_sw.flight_main as fm
    from protocol.codec import decode_message, encode_message
    from protocol.grids import elevation_from_wire
    from protocol.messages import Config, Error, Result

    cam, poses, imgs = _roof_descent((200.0, 100.0), seed=22)
    cfg = {"camera": cam.to_dict(), "budget": "host", "deadline_s": 30.0, "preset": "fast"}
    elevations, priors = {}, {}
    for unit in (1, 10):
        link = _Link()
        fp = fm.FlightProcess(link, fm.FaultPlan())
        config = Config(**cfg, options={"elevation_unit_cm": unit, "link_baud": 921600})
        fp.handle(config)
        priors[unit] = fp.expected_result_bytes(config)
        for f in frames_of("p", 0, list(zip(poses, imgs))):
            fp.handle(f)
        (res,) = [m for m in link.sent if isinstance(m, Result)]
        back = decode_message(encode_message(res))
        assert back.elevation_unit_cm == unit
        elevations[unit] = elevation_from_wire(back.elevation_grid, back.elevation_offset_m, back.elevation_unit_cm)
    assert np.isfinite(elevations[1]).mean() > 0.5
    assert np.array_equal(np.isnan(elevations[1]), np.isnan(elevations[10]))
    assert np.nanmax(np.abs(elevations[10] - elevations[1])) <= 0.05 + 0.005 + 1e-4  # both roundings
    assert priors[10] < 0.9 * priors[1]
    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    fp.handle(Config(**cfg, options={"elevation_unit_cm": 0}))
    (err,) = link.sent
    assert isinstance(err, Error) and err.code == "bad_config" and "elevation_unit_cm" in err.text
    assert fp.config is None


def _result_to_fit():
    """A host-budget Result of a roof pair at the Config's finest steps, for ``fit_to_line``: (flight process, the
    ``_result_message`` arguments, the Result, its line time, a rebuild at other steps, the baud)."""
    import functools

    import flight_sw.flight_main as fm
    from flight_sw.pipeline import run_pipeline
    from protocol.codec import encode_message
    from protocol.messages import Config

    cam, poses, imgs = _roof_descent((200.0, 100.0), seed=22)
    res = run_pipeline(imgs[0], imgs[1], poses[0], poses[1], cam, preset="fast")
    baud = 9600.0  # ~1.1 s per kB: the encoding's own milliseconds do not matter
    cfg = Config(camera=cam.to_dict(), budget="host", deadline_s=30.0, preset="fast",
                 options={"link_baud": baud, "elevation_step": 1, "psafe_step": 1})  # fmt: skip
    fp = fm.FlightProcess(_Link(), fm.FaultPlan())
    args = (res, (1, 2), cfg, res.grid, res.sites, res.info.get("no_site_reason"))
    full = fp._result_message(*args)
    full_s = fm.expected_line_s(len(encode_message(full)), baud)
    return fp, args, full, full_s, functools.partial(fp._result_message, *args), baud


def test_a_result_that_would_miss_its_deadline_on_the_line_goes_out_with_coarser_grids():
    """``fit_to_line``: the elevation step doubles, then the P(safe) step, until the Result's line time fits the time
    left; the state grid and the sites are kept; with time to spare the Result is sent as the Config asks."""
    import time

    import flight_sw.flight_main as fm
    from protocol.codec import encode_message

    fp, args, full, full_s, rebuild, baud = _result_to_fit()
    out, line_s, grown, enc = fm.fit_to_line(full, rebuild, baud, time.monotonic() + 3 * full_s, full_s)
    assert out is full and grown == 1.0 and line_s == full_s and enc is None  # time to spare: not even measured
    smallest = fp._result_message(*args, (fm.MAX_SHRINK_STEP, fm.MAX_SHRINK_STEP))
    small_s = fm.expected_line_s(len(encode_message(smallest)), baud)
    assert small_s < 0.6 * full_s
    left = 0.5 * (full_s + small_s)
    out, line_s, grown, enc = fm.fit_to_line(full, rebuild, baud, time.monotonic() + left, full_s)
    assert out.elevation_step > 1 and line_s <= left and grown > 1.0
    assert np.array_equal(out.state_grid, full.state_grid) and out.sites == full.sites
    assert line_s == pytest.approx(fm.expected_line_s(len(encode_message(out)), baud))
    assert enc is not None and enc.message is out and enc.body == encode_message(out)  # what the link sends
    out, line_s, _, _ = fm.fit_to_line(full, rebuild, baud, time.monotonic(), full_s)  # no time left: the smallest
    assert (out.elevation_step, out.psafe_step) == (fm.MAX_SHRINK_STEP, fm.MAX_SHRINK_STEP)
    out, line_s, grown, enc = fm.fit_to_line(full, rebuild, 0.0, time.monotonic(), 0.0)
    assert out is full and grown == 1.0 and line_s == 0.0 and enc is None  # no line rate (ZeroMQ): sent as it is


def test_a_result_fits_its_line_after_its_encoding_and_is_not_encoded_again(monkeypatch):
    """On a slow processor encoding a Result takes time (0.09 s at 23 % duty). ``fit_to_line`` judges the line
    time against what is left once the Result is encoded, and hands the link that body, so sending does not
    encode it again. Here each encoding takes 0.3 s. With 0.2 s to spare over the line time, one encoding does not
    leave room: the Result goes out coarser (stop 46 sent it as it was, ~0.1 s late). With 0.5 s to spare it goes
    out at the Config's steps, encoded once (stop 47 encoded it twice, and sent it coarser to make room)."""
    import time

    import flight_sw.flight_main as fm
    from protocol.codec import encode, encode_message

    _, _, full, full_s, rebuild, baud = _result_to_fit()
    calls = []

    def slow_encode(msg):
        calls.append(msg)
        time.sleep(0.3)
        return encode(msg)

    monkeypatch.setattr(fm, "encode", slow_encode)
    due = time.monotonic() + full_s + 0.2
    out, line_s, grown, enc = fm.fit_to_line(full, rebuild, baud, due, full_s)
    assert out.elevation_step > 1 and grown > 1.0 and enc is not None and enc.message is out
    assert time.monotonic() + line_s <= due + 0.02  # off the line by its due time
    calls.clear()
    due = time.monotonic() + full_s + 0.5
    out, line_s, grown, enc = fm.fit_to_line(full, rebuild, baud, due, full_s)
    assert out is full and grown == 1.0 and calls == [full]
    assert enc is not None and enc.body == encode_message(full)
    assert time.monotonic() + line_s <= due + 0.02


def test_a_hazard_beside_the_footprints_edge_survives_a_move_onto_a_coarser_grid():
    """A coarser cell was unmapped if any finer part was never mapped, which wiped its hazard call: one later
    result 99.9 % sure then called the hazard safe where the rule asks three (review of stop 64)."""
    prm = FusionParams()
    st = np.full((8, 8), STATE_SAFE, np.uint8)
    ps = np.full((8, 8), 0.999, np.float32)
    st[:, 2:] = STATE_OUTSIDE  # the footprint's edge
    st[3, 1], ps[3, 1] = STATE_UNSAFE, 0.0  # a hazard call beside it
    fm = fuse(None, grid_of(st, ps, origin=(0.0, 7.0)), prm)
    later = uniform(STATE_SAFE, 0.999, shape=(6, 6), origin=(0.0, 7.5), cell=1.5)
    cell = (2, 1)  # the 1.5 m cell holding the hazard's ground (x 1, y 4)
    for n in (1, 2):  # the rule's margin takes three such results (overturn_margin); one did it
        fm = fuse(fm, later, prm)
        state, _ = fused_state(fm, prm)
        assert fm.hazards[cell] == 1 and state[cell] != STATE_SAFE, n
        assert to_hazard_grid(fm, prm).hazard[cell] >= 1.0


def _stub_flight(monkeypatch):
    """A FlightProcess on a collecting link whose pipeline maps a 16 x 16 grid from the upper image alone: dark
    (DN < 100) all hazard calls, bright all safe at 0.999; ``calls`` gets each pair's (upper, lower) mean DN."""
    import types

    import flight_sw.flight_main as fmn

    calls: list[tuple[int, int]] = []

    def pipeline(i1, i2, pose1, pose2, camera, **kw):
        calls.append((int(i1.mean()), int(i2.mean())))
        dark = i1.mean() < 100
        st = np.full((16, 16), STATE_UNSAFE if dark else STATE_SAFE, np.uint8)
        ps = np.full((16, 16), 0.0 if dark else 0.999, np.float32)
        g = HazardGrid(np.where(dark, 1.0, 0.001) * np.ones((16, 16), np.float32), np.zeros((16, 16), np.float32),
                       (0.0, 0.0), 1.0, st, ps)  # fmt: skip
        h, w = i1.shape
        z = np.zeros((h, w), np.float32)
        out = {"info": {}, "grid": g, "sites": [], "params": {"psafe_min": 0.9}, "level": "full", "timings": {}}
        return types.SimpleNamespace(
            **out, degraded=False, hazard=z, elevation=z, state=z.astype(np.uint8), filled=None
        )

    monkeypatch.setattr(fmn, "run_pipeline", pipeline)
    monkeypatch.setattr(fmn, "measured_reserve_ratio", lambda *a, **k: None)
    link = _Link()
    return fmn, fmn.FlightProcess(link, fmn.FaultPlan()), link, calls


def _frame(seq: int, pid: str, idx: int, dn: int, z: float, px: int = 64):
    from protocol.messages import Frame

    R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    return Frame(seq=seq, capture_time_s=float(seq), position_m=(0.0, 0.0, z), R_world_to_cam=R, altimeter_m=z,
                 image=np.full((px, px), dn, np.uint8), pair_id=pid, frame_index=idx)  # fmt: skip


CAM = {"width": 64, "height": 64, "fx": 100.0, "fy": 100.0, "cx": 31.5, "cy": 31.5}


def test_a_second_descent_that_names_no_descent_id_starts_its_own_map(monkeypatch):
    """A ground naming no descent_id flew a second descent with the same Config in one session: its map was fused
    onto the first descent's (another world frame), and a bright descent's first Result read the dark one's
    hazards, or the reverse its safe ground (review of stop 64). The map goes on only under the same descent_id."""
    from protocol.messages import Config, Result

    for options, carried in (({}, False), ({"descent_id": 7}, True)):
        _, fp, link, _ = _stub_flight(monkeypatch)
        fp.handle(Config(camera=CAM, budget="host", deadline_s=30.0, options=options))
        fp.handle(_frame(1, "00-400_200", 0, 20, 400.0))
        fp.handle(_frame(2, "00-400_200", 1, 20, 200.0))
        fp.handle(Config(camera=CAM, budget="host", deadline_s=30.0, options=options))  # B, or A resent
        fp.handle(_frame(3, "00-400_200", 0, 200, 400.0))
        fp.handle(_frame(4, "00-400_200", 1, 200, 200.0))
        last = [m for m in link.sent if isinstance(m, Result)][-1]
        assert (fp.fused.results == 2) is carried
        assert np.all(np.asarray(last.state_grid) == STATE_SAFE) is not carried


def test_half_received_pairs_are_dropped_on_a_new_descent_and_bounded_and_said(monkeypatch):
    """A new descent's Config left the old one's half-received pair, and the next descent's frame completed it:
    the pipeline ran on frames of two descents. A pair whose other frame never came was held for good (200 held
    50 MiB). Both now go, the second with an Error the ground records (review of stop 64)."""
    from protocol.messages import Config, Error

    fmn, fp, link, calls = _stub_flight(monkeypatch)
    fp.handle(Config(camera=CAM, budget="host", deadline_s=30.0, options={"descent_id": 1}))
    fp.handle(_frame(1, "01-300_150", 0, 20, 300.0))  # its lower frame never comes
    fp.handle(Config(camera=CAM, budget="host", deadline_s=30.0, options={"descent_id": 2}))
    fp.handle(_frame(2, "01-300_150", 1, 200, 150.0))
    assert calls == [] and list(fp.pending) == ["01-300_150"]  # the lower frame alone, waiting for its own upper
    for k in range(3 * fmn.MAX_PENDING_PAIRS):
        fp.handle(_frame(10 + k, f"p{k}", 0, 200, 300.0))
    assert len(fp.pending) == fmn.MAX_PENDING_PAIRS
    dropped = [m for m in link.sent if isinstance(m, Error) and m.code == "frame_dropped"]
    # the first by the new descent's Config (said, or its ground waits out its timeout: QA of stop 65), then the bound
    assert [d.seq for d in dropped[:2]] == [1, 2] and "a new descent's Config" in dropped[0].text
    assert len(dropped) == 2 * fmn.MAX_PENDING_PAIRS + 2
    # a late frame of a dropped pair is not held and dropped a second time, nor answered with a second Error (one
    # per pair, protocol.md; QA of stop 85)
    n, sent = len(fp.pending), len(link.sent)
    fp.handle(_frame(99, "p0", 1, 200, 150.0))
    assert len(fp.pending) == n and len(link.sent) == sent


def test_a_new_ground_session_drops_the_old_half_pairs_unsaid_and_keeps_the_descent(monkeypatch):
    """Under ``run`` the flight process was not told of a new ground session: the old session's half pair stayed, and
    8 pairs later came back as a ``frame_dropped`` about a pair the server had closed (a stale error; QA 65f L1).
    The server now passes the new ground's Hello on, as a board's link does."""
    from protocol.messages import Config, Error, Hello, Result

    fmn, fp, link, calls = _stub_flight(monkeypatch)
    cfg = Config(camera=CAM, budget="host", deadline_s=30.0, options={"descent_id": 3})
    fp.handle(cfg)
    fp.handle(_frame(1, "g1:00-400_200", 0, 200, 400.0))
    fp.handle(_frame(2, "g1:00-400_200", 1, 200, 200.0))
    fp.handle(_frame(3, "g1:01-300_150", 0, 200, 300.0))  # the ground is lost before its lower frame
    fp.handle(Hello(role="hil-server", session=9))
    assert fp.pending == {} and fp.config is None
    fp.handle(cfg)  # the same descent in the new session
    for k in range(fmn.MAX_PENDING_PAIRS + 1):
        fp.handle(_frame(10 + 2 * k, f"g2:{k:02d}", 0, 200, 300.0))
        fp.handle(_frame(11 + 2 * k, f"g2:{k:02d}", 1, 200, 150.0))
    assert not [m for m in link.sent if isinstance(m, Error)]
    assert len([m for m in link.sent if isinstance(m, Result)]) == fmn.MAX_PENDING_PAIRS + 2
    assert fp.fused is not None and fp.fused.results == fmn.MAX_PENDING_PAIRS + 2  # the map went on


def test_a_hazard_outside_one_pairs_grid_is_kept_until_a_later_grid_covers_it():
    """The map follows the newest grid: a hazard outside one narrower grid was dropped with it, and one later result
    back over it called it safe, where the rule asks three (review of stop 64)."""
    prm = FusionParams()
    st = np.full((10, 10), STATE_SAFE, np.uint8)
    ps = np.full((10, 10), 0.999, np.float32)
    st[5, 8], ps[5, 8] = STATE_UNSAFE, 0.0  # a hazard call at x 8, y 4
    wide = grid_of(st, ps, origin=(0.0, 9.0))
    narrow = uniform(STATE_SAFE, 0.999, shape=(10, 6), origin=(0.0, 9.0))  # x 0-5: leaves it out
    again = uniform(STATE_SAFE, 0.999, shape=(10, 10), origin=(0.0, 9.0))
    fm = fuse(fuse(None, wide, prm), narrow, prm)
    assert fm.kept is not None and fm.kept.shape == (1, 5) and tuple(fm.kept[0, :2]) == (8.0, 4.0)
    for n in (1, 2):  # as many as with the narrow grid left out
        fm = fuse(fm, again, prm)
        state, _ = fused_state(fm, prm)
        assert fm.hazards[5, 8] == 1 and state[5, 8] != STATE_SAFE, n
    assert fm.kept is None  # put back, not kept twice
    direct = fuse(fuse(fuse(None, wide, prm), again, prm), again, prm)
    assert fm.logodds[5, 8] == pytest.approx(direct.logodds[5, 8], abs=1e-5)  # as if never left out


@pytest.mark.parametrize("ratio", [1, 2, 8])
def test_a_kept_hazard_goes_back_into_every_finer_cell_it_covers(ratio):
    """Put back at its centre alone, a kept 2 m hazard cell gave one cell of a later 0.25 m grid its call, and one
    result 99.9 % sure called the other 63 safe (review of stop 65). Each part gets it, as a move gives it."""
    prm = FusionParams()
    st = np.full((12, 12), STATE_SAFE, np.uint8)
    ps = np.full((12, 12), 0.999, np.float32)
    st[4, 8], ps[4, 8] = STATE_UNSAFE, 0.0  # a 2 m hazard cell centred at x 16, y 14
    wide = grid_of(st, ps, origin=(0.0, 22.0), cell=2.0)
    narrow = uniform(STATE_SAFE, 0.999, shape=(12, 6), origin=(0.0, 22.0), cell=2.0)  # x 0-10: leaves it out
    c = 2.0 / ratio
    n = int(round(24 / c))
    fine = uniform(STATE_SAFE, 0.999, shape=(n, n), origin=(0.0, 22.0 + 1.0 - c / 2), cell=c)
    fine = dataclasses.replace(fine, origin_xy=(-1.0 + c / 2, 23.0 - c / 2))
    for path in ((wide, fine), (wide, narrow, fine)):
        fm = None
        for g in path:
            fm = fuse(fm, g, prm)
        state, _ = fused_state(fm, prm)
        X = fm.origin_xy[0] + np.arange(fm.shape[1]) * fm.cell_m
        Y = fm.origin_xy[1] - np.arange(fm.shape[0]) * fm.cell_m
        inside = (np.abs(Y - 14.0) < 1.0)[:, None] & (np.abs(X - 16.0) < 1.0)[None, :]
        assert inside.sum() == ratio * ratio
        assert np.all(fm.hazards[inside] > 0) and not np.any(state[inside] == STATE_SAFE), (len(path), ratio)


def test_kept_hazards_past_the_cap_are_counted_not_dropped_silently(monkeypatch):
    import flight_sw.fusion as fu

    monkeypatch.setattr(fu, "MAX_KEPT_HAZARDS", 2)
    st = np.full((6, 6), STATE_UNSAFE, np.uint8)
    fm = fuse(None, grid_of(st, np.zeros((6, 6), np.float32)), FusionParams())
    fm = fuse(fm, uniform(STATE_SAFE, 0.999, origin=(100.0, 0.0)), FusionParams())  # a divert: all 36 left out
    assert fm.kept is not None and len(fm.kept) == 2 and fm.kept_dropped == 34


def test_a_map_of_one_result_calls_safe_only_what_it_called_safe_at_the_floor():
    """The module doc: a map of one result holds its P(safe), and its calls are the fusion rule's. A cell the
    result called safe at a P(safe) under p_min is unknown on the map (the first fused Result of a descent read
    CDI 44.0 against 45.2 % alone, which nothing said; QA of stop 74); nothing it did not call safe is safe."""
    prm = FusionParams()
    state = np.array([[STATE_SAFE, STATE_SAFE, STATE_UNKNOWN, STATE_UNSAFE]], np.uint8)
    p_hi = 1 - (1 - prm.p_min) / 2
    g = grid_of(state, np.array([[p_hi, prm.p_min / 2 + 0.3, p_hi, 0.2]], np.float32))
    fused, psafe = fused_state(fuse(None, g, prm), prm)
    assert fused.tolist() == [[STATE_SAFE, STATE_UNKNOWN, STATE_UNKNOWN, STATE_UNSAFE]]
    np.testing.assert_allclose(psafe, g.psafe, rtol=1e-5)


def test_a_pair_refused_frame_by_frame_gets_one_error(monkeypatch):
    """Frames before any Config, and a pair one frame of which has the wrong size, were answered with an Error per
    frame: a board's console counted two pairs answered with an Error for one (QA of stop 85; protocol.md: every
    pair ends in exactly one Result or one Error)."""
    from protocol.messages import Config, Error

    _, fp, link, calls = _stub_flight(monkeypatch)
    fp.handle(_frame(1, "x", 0, 200, 300.0))
    fp.handle(_frame(2, "x", 1, 200, 150.0))
    errors = [m for m in link.sent if isinstance(m, Error)]
    assert [(e.code, e.seq) for e in errors] == [("no_config", 1)]
    fp.handle(Config(camera=CAM, budget="host", deadline_s=30.0, options={"descent_id": 1}))
    fp.handle(_frame(3, "y", 0, 200, 300.0))  # held, then its lower frame is the wrong size
    fp.handle(_frame(4, "y", 1, 200, 150.0, px=32))
    fp.handle(_frame(5, "z", 0, 200, 300.0, px=32))  # the upper one wrong, the lower one right
    fp.handle(_frame(6, "z", 1, 200, 150.0))
    errors = [m for m in link.sent if isinstance(m, Error)]
    assert [(e.code, e.seq) for e in errors] == [("no_config", 1), ("bad_frame", 4), ("bad_frame", 5)]
    assert calls == [] and not fp.pending  # nothing held of the refused pairs
    fp.handle(_frame(7, "x", 0, 200, 300.0))  # the pair refused for want of a Config, sent again after it
    fp.handle(_frame(8, "x", 1, 200, 150.0))
    assert len(calls) == 1


def test_an_altimeter_reading_no_terrain_explains_is_set_aside_and_said(monkeypatch):
    """A reading of 1e300 m failed deep in the range search as a pipeline_failure, and 65535 m at 300 m passed
    unsaid, where the pair reader refuses both (QA of stop 85). The flight side maps the pair without it."""
    from protocol.messages import Config

    fmn, fp, link, calls = _stub_flight(monkeypatch)
    seen: list[list[float]] = []
    stub = fmn.run_pipeline
    monkeypatch.setattr(fmn, "run_pipeline", lambda *a, **kw: seen.append(kw["altimeter_m"]) or stub(*a, **kw))
    fp.handle(Config(camera=CAM, budget="host", deadline_s=30.0, options={}))
    for k, (upper, lower) in enumerate([(1e300, 150.0), (65535.0, 0.0), (310.0, 148.0)]):
        a = dataclasses.replace(_frame(10 + 2 * k, f"p{k}", 0, 200, 300.0), altimeter_m=upper)
        b = dataclasses.replace(_frame(11 + 2 * k, f"p{k}", 1, 200, 150.0), altimeter_m=lower)
        fp.handle(a)
        fp.handle(b)
        notes = fmn._readings_ignored((a, b))
        if k == 0:
            assert len(notes) == 1 and "frame 0: altimeter_m 1e+300 m is implausible" in notes[0], notes
        elif k == 1:
            assert "implausible" in notes[0] and "is no range" in notes[1], notes
        else:
            assert notes == []
    assert np.isnan(seen[0][0]) and seen[0][1] == 150.0
    assert np.isnan(seen[1]).all() and seen[2] == [310.0, 148.0]
    assert len(calls) == 3


def test_the_flight_side_refuses_a_camera_that_cannot_see_the_ground():
    """A camera looking up failed in OpenCV's remap as a pipeline_failure, one looking at the horizon in numpy's
    divide warnings: both are now the pair reader's bad input (QA of stop 85)."""
    from flight_sw.validate import FlightInputError, check_geometry
    from protocol.pairdir import Camera, Pose

    cam = Camera.from_dict(CAM)
    down = Pose(np.array([0.0, 0.0, 300.0]), np.diag([1.0, -1.0, -1.0]))
    check_geometry(cam, [down, down])
    for R in (np.eye(3), np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])):
        with pytest.raises(FlightInputError, match="cannot see the ground"):
            check_geometry(cam, [down, Pose(np.array([0.0, 0.0, 150.0]), R)])
