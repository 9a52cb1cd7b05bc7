"""Boot warm-up (flight_sw.warmup): a deterministic pair whose images fit its poses; the allocator setting takes."""

from __future__ import annotations

import ctypes.util
import os
import sys

import numpy as np
import pytest

from flight_sw.pipeline import PRESETS, run_pipeline
from flight_sw.warmup import boot_warm_up, settle_allocator, warm_up_pair


def test_warm_up_pair_is_seeded_and_its_images_fit_its_poses():
    cam, p1, p2, i1, i2 = warm_up_pair(128, seed=3)
    again = warm_up_pair(128, seed=3)
    assert np.array_equal(i1, again[3]) and np.array_equal(i2, again[4])
    assert not np.array_equal(i1, warm_up_pair(128, seed=4)[3])
    assert i1.dtype == np.uint8 and i1.shape == (128, 128) and i1.std() > 10
    # the images are rendered from flat ground at Z = 0: the pipeline must find it there, densely
    res = run_pipeline(i1, i2, p1, p2, cam, preset=PRESETS["fast"])
    assert res.level == "full"
    z = res.elevation[res.covered]
    assert np.isfinite(z).mean() > 0.8
    assert abs(float(np.nanmedian(z))) < 1.0


def test_boot_warm_up_reports_what_it_did():
    w = boot_warm_up(PRESETS["fast"], size=96)
    assert w["level"] == "full" and w["size_px"] == 96 and w["cpu_s"] > 0
    assert w["allocator_settled"] == (sys.platform.startswith("linux") and settle_allocator())


@pytest.mark.skipif(not sys.platform.startswith("linux") or not ctypes.util.find_library("c"), reason="glibc only")
def test_settle_allocator_takes_on_glibc():
    assert settle_allocator() is True


def test_the_flight_process_starts_no_process_to_settle_its_allocator(monkeypatch):
    """ctypes.util.find_library runs ``ldconfig -p`` in a child; caught before its exec, the child showed the
    flight process's own pages, and the HIL's memory watch, which charges a flight process for its children,
    counted them twice (51 MiB for a 37 MiB process; stop 79)."""
    import subprocess

    def spawned(*args, **kwargs):
        raise AssertionError(f"a process was started: {args}")

    monkeypatch.setattr(subprocess, "Popen", spawned)
    monkeypatch.setattr(os, "fork", spawned)
    assert settle_allocator() is (sys.platform.startswith("linux"))


def test_heap_touched_for_a_camera_stays_inside_the_hil_memory_model():
    # the flight process touches this much heap when a Config names the camera; `run` admits a camera by the
    # HIL's model of the flight process's peak, so the prefault must never be what breaks the ceiling
    from flight_sw.warmup import heap_mib_for
    from hil_server.budgets import FLIGHT_BYTES_PER_PIXEL

    for side in (64, 128, 512, 1024, 2048):
        assert heap_mib_for(side, side) * 2**20 <= FLIGHT_BYTES_PER_PIXEL * side * side
    # and it covers most of a 512 px approach pair's working set above the base (45 MiB; bench/bench_flight_memory.py)
    assert heap_mib_for(512, 512) >= 40
