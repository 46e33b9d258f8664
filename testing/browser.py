"""A real browser's look at a page: Chromium, headless, drawing WebGL with SwiftShader (software,
no GPU), driven over the Chrome DevTools protocol. ``hapticproxy view`` is checked with it (the
3-D scene really drawn by rerun's web viewer, not its "Loading Application Bundle..." page) and
the screenshots in ``docs/`` are taken with it:

    python -m hapticproxy.testing.browser URL OUT.png [--scene] [--click X,Y] [--settle S] [--timeout S]

:func:`capture` opens ``url`` and takes a screenshot every ``poll_s`` until ``ready`` accepts
one (or the time is up: :class:`BrowserError` with the page's console errors, the last screenshot
saved); :func:`scene_drawn` is the check for ``hapticproxy view``'s scene (the proxy's orange
tool and the contacts' red, in the drawing area). Needs Chromium (Debian: ``apt-get install
chromium``), ``websockets`` and ``pillow``; :func:`find_chromium` says where it is, or None.
"""
from __future__ import annotations

import argparse
import base64
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["BrowserError", "Capture", "capture", "find_chromium", "scene_drawn", "CHROMIUM_FLAGS"]

#: WebGL on SwiftShader in a headless Chromium (no GPU, no display); root needs --no-sandbox
CHROMIUM_FLAGS = ("--headless=new", "--no-first-run", "--no-default-browser-check", "--disable-dev-shm-usage",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                  "--hide-scrollbars", "--mute-audio", "--remote-debugging-port=0")


class BrowserError(RuntimeError):
    """The page never passed the check: the message says what was seen and the console errors."""


@dataclass
class Capture:
    png: bytes
    seconds: float                      # from navigation to this screenshot
    verdict: object = None              # what ``ready`` returned for it
    console: list[str] = field(default_factory=list)  # the page's console errors and warnings


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


def rgb_of(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def scene_drawn(png: bytes, *, min_tool_px: int = 2000, min_contact_px: int = 100, top_px: int = 40) -> tuple[bool, dict]:
    """Whether a screenshot of ``hapticproxy view`` shows its scene: enough pixels of the proxy's
    orange tool and of the contacts' red (points and normals), below the viewer's top bar (whose
    "Software rasterizer" warning is orange too). Returns ``(ok, counts)``."""
    a = rgb_of(png)[top_px:]
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    orange = (r > 170) & (g > 70) & (g < 190) & (b < 140) & (r - g > 50) & (g - b > 30)
    red = (r > 120) & (g < 70) & (b < 70) & (r - g > 80)
    counts = {"tool_px": int(orange.sum()), "contact_px": int(red.sum())}
    return counts["tool_px"] >= min_tool_px and counts["contact_px"] >= min_contact_px, counts


class _Tab:
    """One page over the DevTools protocol (synchronous: a command waits for its reply; events
    read meanwhile keep the console's errors)."""

    def __init__(self, ws) -> None:
        self.ws = ws
        self.next_id = 0
        self.console: list[str] = []

    def call(self, method: str, timeout_s: float = 60.0, **params) -> dict:
        self.next_id += 1
        mine = self.next_id
        self.ws.send(json.dumps({"id": mine, "method": method, "params": params}))
        end = time.monotonic() + timeout_s
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, end - time.monotonic())))
            if msg.get("id") == mine:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def _event(self, msg: dict) -> None:
        method, p = msg.get("method"), msg.get("params", {})
        if method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "warning", "assert"):
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", []))
            self.console.append(f"console.{p['type']}: {text.strip()[:500]}")
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            self.console.append(f"exception: {d.get('exception', {}).get('description', d.get('text', ''))[:500]}")
        elif method == "Log.entryAdded" and p.get("entry", {}).get("level") in ("error", "warning"):
            e = p["entry"]
            self.console.append(f"log.{e['level']}: {e.get('text', '')[:500]} ({e.get('url', '')})")



def capture(url: str, out: str | Path | None = None, *, ready=scene_drawn, timeout_s: float = 180.0,
            poll_s: float = 2.0, settle_s: float = 0.0, size=(1280, 900), click=None,
            chromium: str | None = None) -> Capture:
    """Open ``url`` in a headless Chromium and screenshot it every ``poll_s`` until ``ready(png)``
    (``(ok, verdict)``) is ok, then ``settle_s`` more (and a left ``click`` at that ``(x, y)`` of
    the page, e.g. on rerun's time ruler to scrub a replay) and one more screenshot (kept if it is
    still ok); writes it to ``out`` if given. :class:`BrowserError` after ``timeout_s`` (the last
    screenshot written to ``out`` all the same), naming the verdict and the console's errors."""
    exe = chromium or find_chromium()
    if exe is None:
        raise BrowserError("no Chromium found (Debian: apt-get install chromium)")
    profile = tempfile.mkdtemp(prefix="hapticproxy-chromium-")
    flags = list(CHROMIUM_FLAGS) + [f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}"]
    if os.geteuid() == 0:
        flags.append("--no-sandbox")  # Chromium refuses to run as root with its sandbox
    proc = subprocess.Popen([exe, *flags, "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        from websockets.sync.client import connect

        with connect(_page_socket(Path(profile), proc), max_size=None, open_timeout=30) as ws:
            return _shoot(_Tab(ws), url, out, ready, timeout_s, poll_s, settle_s, size, click)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)


def _shoot(tab: _Tab, url: str, out, ready, timeout_s: float, poll_s: float, settle_s: float, size,
           click) -> Capture:
    for domain in ("Page", "Runtime", "Log"):
        tab.call(f"{domain}.enable")
    tab.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1,
             mobile=False)
    t0 = time.monotonic()
    tab.call("Page.navigate", url=url)
    shot = None
    while True:
        _wait(tab, poll_s)
        png = _screenshot(tab)
        if png is None:  # a page that drew no frame in time (a busy machine): the next try
            if shot is None and time.monotonic() - t0 > timeout_s:
                raise BrowserError(f"{url}: no screenshot in {timeout_s:.0f} s; console errors: "
                                   f"{'; '.join(tab.console[-8:]) or 'none'}")
            continue
        ok, verdict = ready(png)
        shot = Capture(png, time.monotonic() - t0, verdict, tab.console)
        if ok:
            _wait(tab, settle_s)
            if click is not None:
                for kind, button, buttons in (("mouseMoved", "none", 0), ("mousePressed", "left", 1),
                                              ("mouseReleased", "left", 0)):
                    tab.call("Input.dispatchMouseEvent", type=kind, x=float(click[0]), y=float(click[1]),
                             button=button, buttons=buttons, clickCount=1)
                    _wait(tab, 0.5)  # egui reads the button's state once a frame: held over frames
                _wait(tab, 2.0)  # a few frames drawn at the new time
            if settle_s > 0 or click is not None:
                png = _screenshot(tab)
                ok2, verdict2 = ready(png) if png is not None else (False, None)
                if ok2:
                    shot = Capture(png, time.monotonic() - t0, verdict2, tab.console)
            break
        if time.monotonic() - t0 > timeout_s:
            if out is not None:
                Path(out).write_bytes(shot.png)
            errors = "; ".join(tab.console[-8:]) or "none"
            raise BrowserError(f"{url}: not drawn after {shot.seconds:.0f} s (last check: {verdict}); "
                               f"console errors: {errors}")
    if out is not None:
        Path(out).write_bytes(shot.png)
    return shot


def _screenshot(tab: _Tab, timeout_s: float = 120.0) -> bytes | None:
    """The page as a PNG; None when the browser drew none within ``timeout_s``."""
    try:
        return base64.b64decode(tab.call("Page.captureScreenshot", timeout_s, format="png")["data"])
    except TimeoutError:
        return None


def _wait(tab: _Tab, seconds: float) -> None:
    """Let the page run ``seconds``, reading its events meanwhile (the console can be chatty)."""
    end = time.monotonic() + seconds
    while True:
        left = end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(1.0, left))
        tab.call("Browser.getVersion")  # answered by the browser, not the busy page: drains the events


def _page_socket(profile: Path, proc: subprocess.Popen, timeout_s: float = 60.0) -> str:
    """The DevTools websocket of the browser's first page (its port from DevToolsActivePort)."""
    port_file = profile / "DevToolsActivePort"
    end = time.monotonic() + timeout_s
    while not (port_file.exists() and port_file.read_text().strip()):
        if proc.poll() is not None:
            raise BrowserError(f"Chromium exited at start (exit code {proc.returncode})")
        if time.monotonic() > end:
            raise BrowserError(f"Chromium did not open its DevTools port within {timeout_s:.0f} s")
        time.sleep(0.1)
    port = int(port_file.read_text().split()[0])
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if pages:
                return pages[0]["webSocketDebuggerUrl"]
        except OSError:
            pass
        if time.monotonic() > end:
            raise BrowserError("Chromium opened no page")
        time.sleep(0.1)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hapticproxy.testing.browser",
                                description="Screenshot a page in a headless Chromium (WebGL on SwiftShader).")
    p.add_argument("url")
    p.add_argument("out", help="the PNG to write")
    p.add_argument("--scene", action="store_true", help="wait until hapticproxy view's scene is drawn")
    p.add_argument("--wait", type=float, default=10.0, help="without --scene: seconds to wait (default 10)")
    p.add_argument("--settle", type=float, default=0.0, help="with --scene: seconds more before the screenshot")
    p.add_argument("--click", metavar="X,Y", help="with --scene: a left click there first (pixels of the page)")
    p.add_argument("--timeout", type=float, default=180.0, help="give up after this many seconds (default 180)")
    p.add_argument("--size", default="1280x900", help="the window WxH (default 1280x900)")
    a = p.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    if a.scene:
        ready, poll = scene_drawn, 2.0
    else:
        ready, poll = (lambda png: (True, None)), a.wait
    try:
        click = tuple(float(v) for v in a.click.split(",")) if a.click else None
        shot = capture(a.url, a.out, ready=ready, poll_s=poll, timeout_s=a.timeout, settle_s=a.settle, size=(w, h),
                       click=click)
    except BrowserError as exc:
        print(f"browser: {exc}", file=sys.stderr)
        return 1
    print(f"browser: {a.out} after {shot.seconds:.1f} s ({shot.verdict})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
