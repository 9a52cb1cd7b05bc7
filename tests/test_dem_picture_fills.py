"""The DEM picture of ``process`` shows its gap fills (flight_sw/pictures.py): darkened and hatched where the
elevation is a fill, with a legend entry, and nothing else of the picture changes."""

from __future__ import annotations

import numpy as np
import pytest

from flight_sw.pictures import FILL_LABEL, FILL_VEIL, dem_figure, fill_veil

H, W = 64, 80
BLOCK = (slice(20, 36), slice(30, 50))  # rows, columns of the fill region


def _dem() -> tuple[np.ndarray, np.ndarray]:
    """A sloping DEM with no elevation along its border, and its sigma."""
    yy, xx = np.mgrid[:H, :W]
    z = (0.05 * xx + 0.02 * yy).astype(np.float32)
    z[:4], z[:, -5:] = np.nan, np.nan
    sigma = np.full((H, W), 0.2, np.float32)
    return z, sigma


def _pixels(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _screen_box(ax, rows: slice, cols: slice, fig_h: int) -> tuple[float, float, float, float]:
    """(row0, row1, col0, col1) in figure pixels (rows down) of the data pixels ``rows`` x ``cols``."""
    (x0, y0), (x1, y1) = ax.transData.transform(
        [(cols.start - 0.5, rows.start - 0.5), (cols.stop - 0.5, rows.stop - 0.5)]
    )
    r0, r1 = sorted((fig_h - y0, fig_h - y1))
    c0, c1 = sorted((x0, x1))
    return r0, r1, c0, c1


@pytest.mark.parametrize("with_sigma", [False, True])
def test_fill_pixels_are_drawn_apart_and_nothing_else_changes(with_sigma):
    import matplotlib.pyplot as plt

    z, sigma = _dem()
    fills = np.zeros((H, W), bool)
    fills[BLOCK] = True
    kw = dict(sigma=sigma if with_sigma else None, fill_fraction=0.06)  # one title for both
    marked = dem_figure(z, filled=fills, **kw)
    plain = dem_figure(z, filled=np.zeros((H, W), bool), **kw)
    a, b = _pixels(marked), _pixels(plain)
    assert a.shape == b.shape
    differ = (a != b).any(axis=2)

    ax = marked.axes[0]
    assert ax.get_title().startswith("computed elevation")
    r0, r1, c0, c1 = _screen_box(ax, *BLOCK, a.shape[0])
    assert r1 - r0 > 30 and c1 - c0 > 30  # the block is large on screen: the margins below are small beside it
    rows, cols = np.mgrid[: a.shape[0], : a.shape[1]]
    inside = (rows > r0 + 2) & (rows < r1 - 3) & (cols > c0 + 2) & (cols < c1 - 3)
    near = (rows >= r0 - 2) & (rows <= r1 + 2) & (cols >= c0 - 2) & (cols <= c1 + 2)
    assert differ[inside].all()  # every fill pixel is darkened (no colour of the terrain map is left as it was)
    # the veil over the unmarked colour, and hatch lines across part of the region (a wide fill reads as hatched)
    rgb, alpha = np.array(FILL_VEIL[:3]) * 255.0, FILL_VEIL[3]
    veiled = b[inside] * (1.0 - alpha) + rgb * alpha
    off = np.abs(a[inside] - veiled).max(axis=1)
    hatched = off > 20
    assert np.median(off) <= 2 and 0.05 < hatched.mean() < 0.6, (np.median(off), hatched.mean())

    legend = ax.get_legend()
    assert legend is not None and [t.get_text() for t in legend.get_texts()] == [FILL_LABEL]
    assert plain.axes[0].get_legend() is None
    lb = legend.get_window_extent(marked.canvas.get_renderer())
    in_legend = (rows >= a.shape[0] - lb.y1 - 1) & (rows <= a.shape[0] - lb.y0 + 1)
    in_legend &= (cols >= lb.x0 - 1) & (cols <= lb.x1 + 1)
    assert not differ[~near & ~in_legend].any(), "the fill marks changed the picture outside the fill region"
    plt.close(marked)
    plt.close(plain)


def test_without_fills_the_picture_is_the_unmarked_one():
    """An empty mask (a pair without shadow) or none at all (a back-end that does not fill): no legend, no veil."""
    import matplotlib.pyplot as plt

    z, sigma = _dem()
    figs = [dem_figure(z, sigma, filled=f) for f in (None, np.zeros((H, W), bool))]
    # a mask on pixels without elevation marks nothing either: a fill always has an elevation
    nowhere = np.zeros((H, W), bool)
    nowhere[:4] = True
    figs.append(dem_figure(z, sigma, filled=nowhere))
    pix = [_pixels(f) for f in figs]
    assert all(np.array_equal(pix[0], p) for p in pix[1:])
    assert all(f.axes[0].get_legend() is None for f in figs)
    for f in figs:
        plt.close(f)


def test_the_veil_covers_exactly_the_fill_pixels():
    fills = np.zeros((5, 7), bool)
    fills[1:3, 2:6] = True
    fills[4, 0] = True
    rgba = fill_veil(fills)
    assert rgba.shape == (5, 7, 4) and rgba.dtype == np.float32
    assert np.array_equal(rgba[..., 3] > 0, fills) and (rgba[fills][:, :3] < 0.2).all()
