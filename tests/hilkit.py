"""Shared by the HIL test modules: a small rendered descent and a run over it."""

from __future__ import annotations

from pathlib import Path

from ground_sim.descent import render_scenario
from hil_server.run import RunConfig, run_descent, scaled_camera


def small_descent(out: Path, pairs: list[str], px: int = 128) -> Path:
    """Render the vertical descent's ``pairs`` at ``px`` x ``px`` into ``out``; returns its manifest."""
    render_scenario("vertical", out, pairs=pairs, camera=scaled_camera(px), progress=False)
    return out / "manifest.json"


def run_hil(manifest: Path, out: Path, link: str, **kw) -> dict:
    """One HIL run of ``manifest`` on the host budget (``kw`` overrides any RunConfig field), quietly."""
    cfg = RunConfig(out=out, manifest=manifest, **{"link": link, "budget": "host", **kw})
    return run_descent(cfg, log=lambda s: None)
