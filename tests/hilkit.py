"""Shared by the HIL test modules: a small rendered descent, a run over it, a body put on a link as it is."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

from sessioncache import made_once

from ground_sim.descent import render_scenario
from hil_server.run import RunConfig, run_descent, scaled_camera


def _not_json(token: str) -> Any:
    raise ValueError(f"{token} is not JSON: a browser's JSON.parse or jq would refuse the file")


def strict_json(path: Path) -> Any:
    """``path`` read as strict JSON (RFC 8259): a bare NaN or Infinity, which Python writes by default, fails."""
    return json.loads(path.read_text(), parse_constant=_not_json)


def one_line_error(capsys, argv: list[str]) -> str:
    """Run the CLI, check exit 2 and one line on stderr without a traceback; return that line."""
    from hil_server.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"hazard-hil {argv[0]}: error: "), err
    return err


# Where small_descent keeps its renders for the session (tests/conftest.py sets it; empty: render every time)
DESCENT_CACHE: list[Path] = []


def small_descent(out: Path, pairs: list[str], px: int = 128) -> Path:
    """Render the vertical descent's ``pairs`` at ``px`` x ``px`` into ``out``; returns its manifest.

    Renders are deterministic, so a session renders each (pairs, px) once and copies it: two dozen modules
    render the same few descents, 2-5 s each. Into a directory that already holds something the render runs
    for real, as the renderer's own handling of an earlier render is then part of what is tested."""
    out = Path(out)

    def render(where: Path) -> None:
        render_scenario("vertical", where, pairs=pairs, camera=scaled_camera(px), progress=False)

    if not DESCENT_CACHE or (out.exists() and any(out.iterdir())):
        render(out)
        return out / "manifest.json"
    done = made_once(DESCENT_CACHE[0], f"{px}px_{'_'.join(p.replace('/', '-') for p in pairs)}", render)
    shutil.copytree(done, out, dirs_exist_ok=True)
    return out / "manifest.json"


def run_hil(manifest: Path, out: Path, link: str, **kw) -> dict:
    """One HIL run of ``manifest`` on the host budget (``kw`` overrides any RunConfig field), quietly, and without
    report.html's pictures unless ``figures=True`` (about 2 s a run: the tests that look at them ask)."""
    cfg = RunConfig(out=out, manifest=manifest, **{"link": link, "budget": "host", "figures": False, **kw})
    summary = run_descent(cfg, log=lambda s: None)
    assert "report_error" not in summary, summary["report_error"]  # the page is drawn after the run, its failure kept
    return summary


def send_raw(link, type_code: int, body: bytes) -> None:
    """Put a message body on ``link``'s wire as it is, past its encoder (what a broken peer sends)."""
    from protocol.links import ZmqLink, _ZOut

    with link._cv:
        if isinstance(link, ZmqLink):
            link._out.append(_ZOut(10_000, "raw", type_code, body, [], time.monotonic(), len(body)))
        else:
            link.arq.submit(type_code, body, "raw", time.monotonic())
        link._cv.notify_all()


def reddish(rgb) -> bool:
    """A saturated colour of red's hue (within 25 degrees): what the reports keep for undetected hazards."""
    import colorsys

    h, s, v = colorsys.rgb_to_hsv(*(float(c) for c in rgb[:3]))
    return s > 0.5 and v > 0.3 and min(h, 1.0 - h) * 360 < 25
