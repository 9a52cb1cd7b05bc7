"""Open a report in headless Chromium and report what a person would see broken.

Talks the Chrome DevTools Protocol over a WebSocket (``websocket-client``):
starts ``chromium --headless --remote-debugging-port=0`` with an empty
profile, navigates to the page, waits for ``load``, then asks the page how
many images it has and how many decoded (``complete && naturalWidth > 0``),
and collects console errors, uncaught exceptions and failed requests.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--remote-debugging-port=0",
    "--remote-allow-origins=*",
)


def chromium_path() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


@dataclass
class PageCheck:
    images: int = 0
    images_loaded: int = 0
    broken_images: list[str] = field(default_factory=list)
    console_errors: list[str] = field(default_factory=list)
    failed_requests: list[str] = field(default_factory=list)
    title: str = ""

    @property
    def ok(self) -> bool:
        return self.images == self.images_loaded and not self.console_errors and not self.failed_requests


class _Cdp:
    def __init__(self, ws_url: str) -> None:
        import websocket

        self.ws = websocket.create_connection(ws_url, timeout=30)
        self.next_id = 0
        self.events: list[dict[str, Any]] = []

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self.events.append(msg)

    def wait_event(self, method: str, timeout: float) -> None:
        end = time.monotonic() + timeout
        if any(e.get("method") == method for e in self.events):
            return
        while time.monotonic() < end:
            self.ws.settimeout(max(0.1, end - time.monotonic()))
            msg = json.loads(self.ws.recv())
            self.events.append(msg)
            if msg.get("method") == method:
                return
        raise TimeoutError(f"no {method} within {timeout} s")


def check_page(path: str | Path, timeout: float = 30.0) -> PageCheck:
    """Load ``path`` (a local HTML file) in headless Chromium; see :class:`PageCheck`."""
    import urllib.request

    exe = chromium_path()
    if exe is None:
        raise FileNotFoundError("chromium is not installed (make test installs Debian's chromium)")
    url = Path(path).resolve().as_uri()
    profile = tempfile.mkdtemp(prefix="hazard-hil-chromium-")
    try:
        # its own session, so the renderer and crashpad children go down with it and stop
        # writing into the profile before the profile is removed
        # and its own temporary files inside the profile: each run left an org.chromium.Chromium.* directory in /tmp
        proc = subprocess.Popen(
            [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
            env={**os.environ, "TMPDIR": profile},
        )
        try:
            port_file = Path(profile) / "DevToolsActivePort"
            end = time.monotonic() + timeout
            while not port_file.is_file() or not port_file.read_text().strip():
                if time.monotonic() > end or proc.poll() is not None:
                    raise RuntimeError("chromium did not open its debugging port")
                time.sleep(0.05)
            port = int(port_file.read_text().split()[0])
            targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
            page = next(t for t in targets if t.get("type") == "page")
            cdp = _Cdp(page["webSocketDebuggerUrl"])
            for domain in ("Page", "Runtime", "Log", "Network"):
                cdp.call(f"{domain}.enable")
            cdp.call("Page.navigate", url=url)
            cdp.wait_event("Page.loadEventFired", timeout)
            # images with loading="lazy" below the fold: scroll through so every one is fetched
            cdp.call(
                "Runtime.evaluate",
                expression="document.querySelectorAll('img').forEach(i => i.loading = 'eager');",
            )
            js = (
                "new Promise(done => { const imgs = Array.from(document.images);"
                " Promise.all(imgs.map(i => i.complete ? 0 : new Promise(r => { i.onload = i.onerror = r; })))"
                " .then(() => done(JSON.stringify({title: document.title, n: imgs.length,"
                " broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.getAttribute('src'))}))); })"
            )
            res = cdp.call("Runtime.evaluate", expression=js, awaitPromise=True, returnByValue=True)
            info = json.loads(res["result"]["value"])
            out = PageCheck(images=info["n"], images_loaded=info["n"] - len(info["broken"]), title=info["title"])
            out.broken_images = info["broken"]
            for e in cdp.events:
                m, p = e.get("method"), e.get("params", {})
                if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                    out.console_errors.append(" ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
                elif m == "Runtime.exceptionThrown":
                    out.console_errors.append(p["exceptionDetails"].get("text", "exception"))
                elif m == "Log.entryAdded" and p["entry"].get("level") == "error":
                    out.console_errors.append(p["entry"].get("text", ""))
                elif m == "Network.loadingFailed":
                    out.failed_requests.append(f"{p.get('errorText')} ({p.get('requestId')})")
            cdp.ws.close()
            return out
        finally:
            _stop_group(proc)
    finally:
        _remove_profile(Path(profile))


def _stop_group(proc: subprocess.Popen[bytes]) -> None:
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue
        # the leader is gone; give straggling children of the group a moment to exit too
        end = time.monotonic() + wait
        while time.monotonic() < end:
            try:
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)


def _remove_profile(profile: Path) -> None:
    # a child that outlived the group kill can still be flushing files: retry, then say so
    for _ in range(20):
        shutil.rmtree(profile, ignore_errors=True)
        if not profile.exists():
            return
        time.sleep(0.1)
    warnings.warn(f"could not remove the chromium profile {profile}", stacklevel=2)


def browser_available() -> bool:
    """True when a report test should open a browser: chromium is here, or ``make test`` demands it.

    ``make test`` installs chromium and sets ``HAZARD_HIL_REQUIRE_BROWSER``, so there a missing
    browser fails the test (check_page raises) instead of skipping it.
    """
    return chromium_path() is not None or bool(os.environ.get("HAZARD_HIL_REQUIRE_BROWSER"))
