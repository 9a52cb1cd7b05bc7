"""The truth hazard from each pixel's true ground point (ground_sim.truth.hazard_from_points), on surfaces
whose answer is known: DESIGN.md's slope and roughness rules over the 3 m footprint."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ground_sim.truth import hazard_from_points


def _points(z_of, step: float = 0.25, n: int = 120) -> np.ndarray:
    """A nadir-like view: an n x n lattice of ground points ``step`` m apart, heights ``z_of(X, Y)``."""
    g = (np.arange(n) - n / 2) * step
    X, Y = np.meshgrid(g, g)
    return np.stack([X, Y, z_of(X, Y)], axis=-1)


@pytest.mark.parametrize("deg", [5.0, 10.0, 20.0])
def test_a_tilted_plane_reads_its_slope(deg):
    h = hazard_from_points(_points(lambda X, Y: math.tan(math.radians(deg)) * X))
    inner = h[10:-10, 10:-10]
    assert np.isfinite(inner).all()
    assert np.allclose(inner, min(deg / 15.0, 1.0), atol=0.02)


def test_a_boulder_is_rough_where_it_stands_and_not_metres_away():
    def z(X, Y):
        return np.where(np.hypot(X - 1.0, Y + 2.0) < 0.5, 0.6, 0.0)  # 1 m wide, 0.6 m high

    P = _points(z)
    h = hazard_from_points(P)
    d = np.hypot(P[..., 0] - 1.0, P[..., 1] + 2.0)
    assert (h[d < 0.4] >= 1).all()  # on top of it: 0.6 m over a plane it lifts only a little
    inner = np.zeros(h.shape, bool)
    inner[10:-10, 10:-10] = True  # the border band sees under half a footprint: no truth there
    assert np.isfinite(h[inner]).all() and (h[inner & (d > 3.5)] < 0.05).all()  # a footprint away: untouched


def test_unseen_ground_is_unknown_and_the_seen_rest_is_not():
    P = _points(lambda X, Y: 0.1 * X)
    P[:, 60:] = np.nan  # half the view without ground points
    h = hazard_from_points(P)
    assert np.isnan(h[:, 60:]).all()
    assert np.isfinite(h[10:-10, 5:50]).all()


def test_ground_sampled_coarser_than_half_the_footprint_gives_no_truth():
    """2 m between pixels: a 3 m footprint spans under two of them; its slope is not in the data."""
    h = hazard_from_points(_points(lambda X, Y: 0.0 * X, step=2.0, n=60))
    assert np.isnan(h).all()


def test_the_true_shadow_makes_a_pixel_unsafe():
    P = _points(lambda X, Y: 0.0 * X)
    shadow = np.zeros(P.shape[:2], bool)
    shadow[40:50, 40:50] = True
    h = hazard_from_points(P, shadow)
    assert (h[40:50, 40:50] == 1).all() and (h[60:-10, 60:-10] < 0.05).all()
