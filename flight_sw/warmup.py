"""Boot-time warm-up: one small synthetic pair through the pipeline before the first real one.

**Why.** A fresh process pays one-off costs on its first pair: glibc maps every array above its
mmap threshold (128 kB at start) with fresh pages and unmaps it on free, the heap's new pages
fault in on first touch, and OpenCV and the pose refinement set themselves up on first call.
In the HIL those costs are paid at the emulated processor's speed inside the first deadline,
and the anytime clock reads them as a slow processor. So the flight process runs
:func:`boot_warm_up` at boot, before it says Hello (the supervisor starts no deadline until
then), and :func:`prefault_heap` when a Config names a new camera (the heap's size depends on
the camera; the frames are still on the line then).

Measured with ``bench/bench_first_pair.py`` on a held-out thesis vertical 600/300 pair, one
pinned core, the first pair's CPU against the steady CPU of the next two, medians of 9 fresh
processes: cold 1.33x (305 ms); after :func:`boot_warm_up` 1.12x (265 ms); with
:func:`prefault_heap` as well 0.99x (251 ms). :func:`settle_allocator` alone gave 1.16-1.18x.

The pair is a seeded, textured flat ground seen by two nadir cameras at 600 m and 300 m (the
thesis camera scaled to ``size`` px). Both images are rendered with the pipeline's own geometry
(:func:`flight_sw.georef.backproject`), so the warm-up runs every stage a real pair runs.
"""

from __future__ import annotations

import ctypes
import time
from typing import Any

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

from .georef import backproject
from .pipeline import Params, run_pipeline

# glibc mallopt(3) parameters
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_B = 32 * 2**20  # glibc's ceiling for the dynamic threshold: arrays up to this come from the heap
TRIM_THRESHOLD_B = 128 * 2**20  # keep up to this much freed heap for the next pair instead of returning it

NADIR_R = np.diag([1.0, -1.0, -1.0])  # x right = +X, y down = -Y, optical axis = -Z


def warm_up_pair(size: int = 128, seed: int = 0) -> tuple[Camera, Pose, Pose, np.ndarray, np.ndarray]:
    """``(camera, pose1, pose2, i1, i2)``: flat textured ground, nadir views from 600 m and 300 m.

    Texture: seeded uniform noise at 0.25 m, smoothed over about a metre, with a few dark spots
    (matchable features for the pose refinement); grey levels in 20-230.
    """
    f = (size / 2.0) / np.tan(np.radians(15.0))  # the thesis camera's 30 deg field of view
    cam = Camera(size, size, f, f, (size - 1) / 2.0, (size - 1) / 2.0)
    p1 = Pose(np.array([0.0, 0.0, 600.0]), NADIR_R)
    p2 = Pose(np.array([0.0, 0.0, 300.0]), NADIR_R)
    rng = np.random.default_rng(seed)
    half = 0.6 * 600.0 * (size / 2.0) / f + 10.0  # covers i1's footprint
    gsd = 0.25 * 300.0 / f * (512.0 / size)
    n = int(np.ceil(2 * half / gsd))
    tex = cv2.GaussianBlur(rng.random((n, n), dtype=np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / max(float(tex.max() - tex.min()), 1e-6)
    for x, y in rng.integers(0, n, size=(max(8, n * n // 4000), 2)):
        cv2.circle(tex, (int(x), int(y)), int(rng.integers(2, 6)), 0.05, -1)
    tex = (20.0 + 210.0 * tex).astype(np.float32)
    zero = np.zeros((size, size))
    images = []
    for pose in (p1, p2):
        X, Y = backproject(cam, pose, zero)
        mx = ((X + half) / gsd - 0.5).astype(np.float32)
        my = ((half - Y) / gsd - 0.5).astype(np.float32)
        img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        images.append(np.clip(img, 0, 255).astype(np.uint8))
    return cam, p1, p2, images[0], images[1]


def settle_allocator() -> bool:
    """Let the next pairs reuse the heap the first one grew (glibc only; False elsewhere).

    glibc maps every allocation above its mmap threshold (128 kB at start, raised only by the first
    free of a larger mapped block) with its own ``mmap``/``munmap`` and fresh pages, and returns freed
    heap above the trim threshold to the kernel. Fixing both (``mallopt``) makes a pair's arrays
    (a 512 px cost slab is a few MiB) come from heap pages an earlier pair already touched. The
    address space is the same as the largest pair's, which the memory ceiling bounds anyway.

    ``mallopt`` is looked up among the symbols the process has loaded (``dlopen(NULL)``), not with
    ``ctypes.util.find_library``: that runs ``ldconfig -p`` in a child process, and a child not yet
    past its ``exec`` shows the flight process's own pages as its RssAnon. The HIL's memory watch
    charges a flight process for its children, so it read the flight process twice (a 128 px
    camera at 51 MiB against its 37 MiB; stop 79).
    """
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_B) == 1
    return bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_B) == 1 and ok)


# the flight pipeline's working set per camera pixel, less the process's base: an oblique approach pair's grid
# needs ~185 B (45 MiB at 512 px), a nadir pair's ~150 B (bench/bench_flight_memory.py, stop 35; stop 33 measured
# 260 and 190 B and set 250). At 150 B an approach pair's first slope stage had cost 150 ms of CPU instead of 32
# (page faults), and every later one 72 ms (docs/hil.md, "Boot warm-up"). More than the pipeline needs is not free:
# the heap keeps it, and at 1024 px a 250 B prefault raised the process's peak from 219 to 275 MiB
HEAP_BYTES_PER_PIXEL = 180


def heap_mib_for(width: int, height: int) -> int:
    """MiB of heap worth touching ahead of the first pair of a ``width`` x ``height`` camera."""
    return int(HEAP_BYTES_PER_PIXEL * max(0, width) * max(0, height) / 2**20)


def prefault_heap(mib: int) -> None:
    """Grow the heap by ``mib`` MiB of touched pages and free them again.

    With :func:`settle_allocator` in force glibc keeps them, so the first pair finds its working
    set mapped instead of taking a page fault on every new page. Blocks of 2 MiB stay under the
    mmap threshold; freed, they merge into one free chunk below the trim threshold.
    """
    blocks = [np.ones(2**19, np.float32) for _ in range(max(0, int(mib)) // 2)]
    del blocks


def warm_up(preset: Params, size: int = 128, seed: int = 0) -> dict[str, Any]:
    """Run one synthetic pair (:func:`warm_up_pair`) through ``preset``; its telemetry.

    Returns ``{"cpu_s", "wall_s", "size_px", "level"}``. Nothing of the run is kept.
    """
    c0, w0 = time.thread_time(), time.monotonic()
    cam, p1, p2, i1, i2 = warm_up_pair(size, seed)
    res = run_pipeline(i1, i2, p1, p2, cam, preset=preset)
    return {
        "cpu_s": time.thread_time() - c0,
        "wall_s": time.monotonic() - w0,
        "size_px": int(size),
        "level": str(res.level),
    }


def boot_warm_up(preset: Params, size: int = 128) -> dict[str, Any]:
    """What the flight process does at boot: :func:`settle_allocator`, then :func:`warm_up`.

    Returns the warm-up's telemetry plus ``allocator_settled``.
    """
    settled = settle_allocator()
    return {**warm_up(preset, size), "allocator_settled": settled}
