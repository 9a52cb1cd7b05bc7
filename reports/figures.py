"""Figure building blocks: colour maps with NaN as black, titled panels with a colour ramp, PNG output.

Confusion colours follow DESIGN.md's scoring convention (positive = safe): a
TP is safe ground called safe, an FP an undetected hazard.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

# Confusion overlay colours (BGR): positive = safe (DESIGN.md).
CONFUSION_BGR = {
    "TP": (80, 175, 76),
    "TN": (54, 67, 244),
    "FP": (255, 0, 255),
    "FN": (180, 180, 180),
    "none": (0, 0, 0),
}
PANEL_PX = 200


def save_figure(fig, path: str | Path) -> Path:
    """Write ``fig`` as a PNG (creating the folder) and release it."""
    import matplotlib.pyplot as plt

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def fmt_number(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return str(v)
    if isinstance(v, (float, np.floating)):
        a = abs(float(v))
        if a != 0 and (a >= 1e4 or a < 1e-3):
            return f"{v:.2e}"
        return f"{v:.{max(0, digits - 1 - int(math.floor(math.log10(a))))}f}" if a else "0"
    return str(v)


def colorize(a: np.ndarray, lo: float, hi: float, cmap: int | None = None) -> np.ndarray:
    """BGR uint8 image of ``a`` mapped linearly from [lo, hi] through an OpenCV colormap; NaN -> black."""
    import cv2

    cmap = cv2.COLORMAP_VIRIDIS if cmap is None else cmap
    span = hi - lo if hi > lo else 1.0
    x = np.clip((np.nan_to_num(a, nan=lo) - lo) / span, 0, 1)
    img = cv2.applyColorMap((x * 255).astype(np.uint8), cmap)
    img[~np.isfinite(a)] = 0
    return img


def panel(
    img: np.ndarray,
    title: str,
    lo: float | None = None,
    hi: float | None = None,
    cmap: int | None = None,
    px: int = PANEL_PX,
) -> np.ndarray:
    import cv2

    t = cv2.resize(img, (px, px), interpolation=cv2.INTER_AREA)
    bar_h = 14 if lo is not None else 0
    t = cv2.copyMakeBorder(t, 18, 4 + bar_h, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
    cv2.putText(t, title, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    if lo is not None and hi is not None:
        ramp = colorize(np.tile(np.linspace(lo, hi, px // 2)[None, :], (6, 1)), lo, hi, cmap)
        y = 18 + px + 2
        t[y : y + 6, 2 : 2 + px // 2] = ramp
        cv2.putText(
            t,
            f"{fmt_number(lo, 2)} .. {fmt_number(hi, 2)}",
            (px // 2 + 8, y + 7),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.33,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return t


def triptych(
    est: np.ndarray,
    truth: np.ndarray,
    names: tuple[str, str, str],
    unit: str,
    err_limit: float | None = None,
    px: int = PANEL_PX,
) -> np.ndarray:
    """Computed | ground truth | error (est - truth), like thesis appendices G/J/L. Returns BGR uint8.

    Computed and truth share one colour range (2nd-98th percentile of the
    truth); the error uses a symmetric diverging range (``err_limit`` or the
    95th percentile of |error|).
    """
    import cv2

    fin = truth[np.isfinite(truth)]
    lo, hi = (float(np.percentile(fin, 2)), float(np.percentile(fin, 98))) if fin.size else (0.0, 1.0)
    err = est - truth
    fe = np.abs(err[np.isfinite(err)])
    lim = err_limit or (float(np.percentile(fe, 95)) if fe.size else 1.0) or 1.0
    return np.hstack(
        [
            panel(colorize(est, lo, hi), f"{names[0]} [{unit}]", lo, hi, px=px),
            panel(colorize(truth, lo, hi), f"{names[1]} [{unit}]", lo, hi, px=px),
            panel(
                colorize(err, -lim, lim, cv2.COLORMAP_COOL), f"{names[2]} [{unit}]", -lim, lim, cv2.COLORMAP_COOL, px=px
            ),
        ]
    )


def confusion_image(hazard_est: np.ndarray, hazard_true: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """BGR map of TP/TN/FP/FN per pixel (positive = safe; NaN estimate = unsafe, as in scoring)."""
    eu = ~(np.asarray(hazard_est, np.float64) < 1.0)  # NaN (not assessed) lands on the unsafe side
    tu = np.asarray(hazard_true) >= 1.0
    keep = np.asarray(covered, bool) & np.isfinite(hazard_true)
    out = np.zeros(hazard_true.shape + (3,), np.uint8)
    for name, m in (("TP", ~eu & ~tu), ("TN", eu & tu), ("FP", ~eu & tu), ("FN", eu & ~tu)):
        out[m & keep] = CONFUSION_BGR[name]
    return out


def hazard_figure(
    image: np.ndarray,
    hazard_est: np.ndarray,
    hazard_true: np.ndarray,
    covered: np.ndarray,
    epipole_box: np.ndarray | None = None,
    px: int = PANEL_PX,
) -> np.ndarray:
    """Input i1 | computed hazard | true hazard | confusion overlay (thesis appendix H)."""
    import cv2

    gray = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    conf = confusion_image(hazard_est, hazard_true, covered)
    if epipole_box is not None and epipole_box.any():
        rows, cols = np.nonzero(epipole_box)
        cv2.rectangle(
            conf,
            (int(cols.min()), int(rows.min())),
            (int(cols.max()), int(rows.max())),
            (255, 255, 255),
            max(1, image.shape[0] // 256),
        )
    panels = [
        panel(gray, "i1", px=px),
        panel(colorize(hazard_est, 0, 1, 2), "computed hazard", px=px),
        panel(colorize(hazard_true, 0, 1, 2), "true hazard", px=px),
        panel(conf, "TP green TN red FP magenta FN gray", px=px),
    ]
    return np.hstack(panels)


def write_png(path: str | Path, img: np.ndarray) -> Path:
    import cv2

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(p), img, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f"could not write {p}")
    return p
