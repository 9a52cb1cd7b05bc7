"""The grid the site search reads keeps every hazard the pixel map calls (review of stop 64, F2)."""

import numpy as np
import pytest

from flight_sw.evidence import grid_evidence, hold_unsafe_pixels
from flight_sw.mapping import remap_maps, remap_with
from protocol.pairdir import STATE_SAFE, STATE_UNSAFE

H = W = 40


def _grid(state: np.ndarray, ps: np.ndarray, off: float):
    """The calibrated path's pull onto a grid of one-pixel cells whose centres sit ``off`` px from the pixels'."""
    gv, gu = np.mgrid[0 : H - 1, 0 : W - 1].astype(np.float64) + off
    maps = remap_maps(gu, gv)
    g_call = remap_with((state == STATE_SAFE).astype(np.float32), maps) > 0.5
    g_bad = remap_with((state == STATE_UNSAFE).astype(np.float32), maps) > 0.5
    cov = np.ones(g_call.shape, bool)
    gev = grid_evidence(g_call, g_bad, remap_with(ps, maps), cov, None, 1.0, None, measured=cov)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return gev, remap_maps(u - off, v - off)  # each pixel's cell coordinates


@pytest.mark.parametrize("off", [0.0, 0.2, 0.3, 0.5])
def test_a_one_pixel_hazard_stays_on_the_grid_wherever_the_cells_fall(off):
    """A one-pixel hazard (a small rock's shadow) with no cell centre within ~0.3 px was lost by the bilinear pull:
    every cell around it read safe, and a site could be centred on it."""
    state = np.full((H, W), STATE_SAFE, np.uint8)
    state[20, 20] = STATE_UNSAFE
    ps = np.full((H, W), 0.99, np.float32)
    ps[20, 20] = 0.0
    gev, px = _grid(state, ps, off)
    held, n = hold_unsafe_pixels(gev, state == STATE_UNSAFE, ps, px)
    assert (held.state == STATE_UNSAFE).sum() >= 1
    cell = tuple(np.argwhere(held.state == STATE_UNSAFE)[0])
    assert abs(cell[0] - (20 - off)) <= 0.5 and abs(cell[1] - (20 - off)) <= 0.5  # the cell its ground falls in
    assert held.hazard[cell] == 1.0 and held.psafe[cell] <= ps[20, 20] + 0.4
    assert n == (0 if off < 0.25 else 1)  # the pull alone kept it near a centre, and lost it farther off


def test_an_unsafe_regions_edge_does_not_erode_the_safe_ground():
    """Along a region's edge the cell that holds an unsafe pixel is already mostly unsafe: nothing changes."""
    state = np.full((H, W), STATE_SAFE, np.uint8)
    state[:, :17] = STATE_UNSAFE
    ps = np.where(state == STATE_SAFE, 0.99, 0.1).astype(np.float32)
    for off in (0.0, 0.3, 0.5):
        gev, px = _grid(state, ps, off)
        held, n = hold_unsafe_pixels(gev, state == STATE_UNSAFE, ps, px)
        assert n == 0 and np.array_equal(held.state, gev.state)
