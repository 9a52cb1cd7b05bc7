"""Reference workload: a fixed slice of the flight software's own operation mix.

One *unit* is eight steps of a plane sweep on a 512x512 image pair (the thesis
camera, DESIGN.md): per step a plane-induced homography built in numpy with
ordinary Python overhead (H = K (R - t n^T / d) K^-1, DESIGN.md / thesis eq. 3.8),
``cv2.warpPerspective`` with bilinear interpolation (thesis section 4.2),
``cv2.absdiff`` and a 17x17 un-normalised ``cv2.boxFilter`` (the SAD window of
thesis section 4.3), then a winner-take-all update of the best cost and plane
index. The speed of a core is its rate in units per CPU-second on one thread.

The rate is measured on CPU time (``time.process_time``), not wall time, so
that other processes sharing the host shift it little; the median over many
units rejects the odd slow unit (cache eviction, frequency change).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import numpy as np

IMAGE_SIZE = 512
PLANES_PER_UNIT = 8
SAD_WINDOW = 17
_SEED = 20240611


@dataclass(frozen=True)
class WorkloadRate:
    """Result of a reference-workload run."""

    units_per_s: float  # median rate, units per CPU-second
    spread: float  # (p90 - p10) / median of the per-batch rates
    units: int  # units executed
    cpu_s: float  # CPU time spent
    checksum: int  # proves the work was done identically each time


def make_inputs(seed: int = _SEED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Deterministic textured image pair (float32 in [0, 1]) and intrinsics K."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.random((IMAGE_SIZE, IMAGE_SIZE), dtype=np.float32)
    img1 = cv2.GaussianBlur(noise, (0, 0), 2.0)
    img2 = cv2.GaussianBlur(np.roll(noise, 3, axis=1), (0, 0), 2.0)
    f = 955.405
    c = (IMAGE_SIZE - 1) / 2.0
    K = np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])
    return img1, img2, K


def run_unit(img1: np.ndarray, img2: np.ndarray, K: np.ndarray) -> int:
    """One unit of work; returns a checksum of the winning plane indices."""
    import cv2

    Kinv = np.linalg.inv(K)
    n = np.array([0.0, 0.0, 1.0])
    R = np.eye(3)
    t = np.array([0.0, 0.0, -500.0])  # the lower camera, half the altitude of the upper
    best = np.full(img1.shape, np.inf, dtype=np.float32)
    index = np.zeros(img1.shape, dtype=np.int16)
    for k in range(PLANES_PER_UNIT):
        d = -1000.0 + 0.15 * k  # planes 15 cm apart, as the thesis's depth step
        H = K @ (R - np.outer(t, n) / d) @ Kinv
        H /= H[2, 2]
        warped = cv2.warpPerspective(img2, H, (IMAGE_SIZE, IMAGE_SIZE), flags=cv2.INTER_LINEAR)
        sad = cv2.boxFilter(cv2.absdiff(img1, warped), -1, (SAD_WINDOW, SAD_WINDOW), normalize=False)
        better = sad < best
        best = np.where(better, sad, best)
        index[better] = k
    return int(index.astype(np.int64).sum() % 1_000_003)


def measure_rate(seconds: float = 1.0, batch: int = 2) -> WorkloadRate:
    """Run units on one OpenCV thread for about ``seconds`` of CPU time.

    rate = batch / (CPU time of the batch), median over batches.
    """
    import cv2

    if not seconds > 0:
        raise ValueError(f"seconds must be > 0, got {seconds}")
    img1, img2, K = make_inputs()
    previous_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # one emulated core: never let OpenCV fan out
    try:
        checksum = run_unit(img1, img2, K)  # warm-up: caches, lazy init
        rates: list[float] = []
        units = 0
        start = time.process_time()
        while True:
            t0 = time.process_time()
            for _ in range(batch):
                if run_unit(img1, img2, K) != checksum:
                    raise RuntimeError("reference workload is not deterministic")
            dt = time.process_time() - t0
            units += batch
            rates.append(batch / max(dt, 1e-9))
            if time.process_time() - start >= seconds and len(rates) >= 3:
                break
        cpu_s = time.process_time() - start
    finally:
        cv2.setNumThreads(previous_threads)
    rates.sort()
    median = statistics.median(rates)
    p10 = rates[int(0.1 * (len(rates) - 1))]
    p90 = rates[int(round(0.9 * (len(rates) - 1)))]
    return WorkloadRate(median, (p90 - p10) / median, units, cpu_s, checksum)


if __name__ == "__main__":
    r = measure_rate(3.0)
    print(f"{r.units_per_s:.3f} units/s (spread {r.spread:.1%}, {r.units} units, checksum {r.checksum})")
