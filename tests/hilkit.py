"""Shared by the HIL test modules: a small rendered descent, a run over it, a body put on a link as it is."""

from __future__ import annotations

import time
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


def send_raw(link, type_code: int, body: bytes) -> None:
    """Put a message body on ``link``'s wire as it is, past its encoder (what a broken peer sends)."""
    from protocol.links import ZmqLink, _ZOut

    with link._cv:
        if isinstance(link, ZmqLink):
            link._out.append(_ZOut(10_000, "raw", type_code, body, [], time.monotonic(), len(body)))
        else:
            link.arq.submit(type_code, body, "raw", time.monotonic())
        link._cv.notify_all()
