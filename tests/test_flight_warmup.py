"""Boot warm-up (flight_sw.warmup): a deterministic pair whose images fit its poses; the allocator setting takes."""

from __future__ import annotations

import ctypes.util
import sys

import numpy as np
import pytest

from flight_sw.pipeline import PRESETS, run_pipeline
from flight_sw.warmup import boot_warm_up, planning_probe, probe_fits, probe_size, settle_allocator, warm_up_pair


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


def test_planning_probe_runs_only_where_it_ends_before_the_frames_are_in():
    px = 512 * 512
    assert probe_fits(px, 1.0 / 0.2107, 921600)  # snapdragon801 on its serial line: ~1.4 s against 2.8 s a frame
    assert not probe_fits(px, 90.9, 921600)  # rad750: ~27 s, the pair's frames are in long before
    assert not probe_fits(px, 1.0, 0)  # zmq or a local link: no line rate, frames arrive at once
    assert probe_fits(px, 1.0, 115200) and not probe_fits(px, 1.0 / 0.2107, 4_000_000)
    assert not probe_fits(0, 1.0, 921600) and not probe_fits(px, float("nan"), 921600)


def test_planning_probe_measures_the_reserved_work_on_a_pair_of_the_cameras_size():
    pr = planning_probe(PRESETS["fast"], 200 * 150)
    assert pr["level"] == "full" and pr["size_px"] == 173 and pr["cpu_s"] > 0
    assert pr["ratio"] is not None and 0 < pr["ratio"] < 50  # unthrottled: a fraction of the reserve, with room
    assert probe_size(4096 * 4096) == 1024 and probe_size(10) == 32  # bounded both ways
    assert planning_probe(PRESETS["thesis"], 64 * 64)["ratio"] is None  # the v1 flow plans no mapping reserve


@pytest.mark.skipif(not sys.platform.startswith("linux") or not ctypes.util.find_library("c"), reason="glibc only")
def test_settle_allocator_takes_on_glibc():
    assert settle_allocator() is True


def test_heap_touched_for_a_camera_stays_inside_the_hil_memory_model():
    # the flight process touches this much heap when a Config names the camera; `run` admits a camera by the
    # HIL's model of the flight process's peak, so the prefault must never be what breaks the ceiling
    from flight_sw.warmup import heap_mib_for
    from hil_server.budgets import FLIGHT_BYTES_PER_PIXEL

    for side in (64, 128, 512, 1024, 2048):
        assert heap_mib_for(side, side) * 2**20 <= FLIGHT_BYTES_PER_PIXEL * side * side
    assert heap_mib_for(512, 512) >= 32  # and it covers most of a 512 px pair's working set (~40 MiB)
