"""``hapticproxy view`` in a real browser: rerun's web viewer, served by the command, opened in a
headless Chromium that draws WebGL in software (SwiftShader), shows the scene (the proxy's tool
and the contacts' red, counted in screenshots by ``testing.browser.scene_drawn``), not its
"Loading Application Bundle..." page: a recording replayed, and a live server with pybullet's
cube resting on its floor. Slow (a software-rendered page takes 30 s to minutes on a busy 2-core
machine): ``.venv/bin/python -m pytest tests/server/test_view_browser.py -m slow``. The check
itself and the screenshots in docs/ run in the default suite."""
from __future__ import annotations

import importlib.util
import io
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hapticproxy.testing.browser import capture, find_chromium, scene_drawn

ROOT = Path(__file__).resolve().parents[2]
HAPTICPROXY = [sys.executable, "-m", "hapticproxy.cli.main"]
_MISSING = [m for m in ("rerun", "websockets", "PIL") if importlib.util.find_spec(m) is None]
_NEEDS = pytest.mark.skipif(
    bool(_MISSING) or find_chromium() is None,
    reason=(f"{', '.join(_MISSING)} not installed (the view, devices and plots extras)" if _MISSING else
            "no Chromium (Debian: apt-get install chromium): the browser check of hapticproxy view needs it"))


def _port(kind=socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _png(rgb: np.ndarray) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(rgb.astype(np.uint8)).save(out, format="PNG")
    return out.getvalue()


# ------------------------------------------------------------------ the check (default suite)
def test_the_scene_check_tells_the_scene_from_the_loading_page():
    pytest.importorskip("PIL")
    page = np.full((900, 1280, 3), 255)
    assert not scene_drawn(_png(page))[0]                       # blank (the loading page: grey text)
    page[10:30, 100:200] = (255, 140, 26)                       # rerun's orange warning in its top bar only
    assert not scene_drawn(_png(page))[0]
    page[300:500, 400:700] = (240, 150, 80)                     # a lit orange box
    assert scene_drawn(_png(page)) == (False, {"tool_px": 60000, "contact_px": 0})  # no contacts
    page[520:540, 450:460] = (200, 30, 30)                      # a red normal
    assert scene_drawn(_png(page))[0]


@pytest.mark.parametrize("name", ["view_live.png", "view_replay.png"])
def test_the_screenshots_in_docs_show_the_scene(name):
    """The screenshots the README shows pass the same check as the browser tests below."""
    pytest.importorskip("PIL")
    ok, counts = scene_drawn((ROOT / "docs" / name).read_bytes())
    assert ok, counts


# ------------------------------------------------------------------ a real browser (slow)
def _recording(path: Path) -> None:
    """A second of a 40 mm cube (the spatial kind's shape) resting on a floor at z = 0, its four
    bottom corners in contact, the hand pushing 0.5 N down and the floor pushing back."""
    from hapticproxy.server import recording
    from hapticproxy.server.shm import NTEL, TEL

    n = 1000
    flat = np.zeros((n, NTEL))
    flat[:, TEL["t_s"]] = np.arange(n) * 1e-3
    for who in ("dev", "proxy"):
        flat[:, TEL[f"{who}_z"]] = 0.02
        flat[:, TEL[f"{who}_qw"]] = 1.0
    flat[:, TEL["cmd_fz"]] = 0.5
    flat[:, TEL["env_fz"]] = 0.5
    flat[:, TEL["loop_state"]] = 2
    flat[:, TEL["gain"]] = 1.0
    flat[:, TEL["contacts"]] = 4
    w = recording.McapRecorder(path, rate_hz=1000.0, config={"device": {"kind": "spatial"}}, t0_epoch_ns=10**18,
                               meta={"tool_kind": "spatial"})
    hdr = np.zeros((), dtype=[("t_s", "f8"), ("env_time_s", "f8"), ("update", "i8"), ("count", "i8")])
    hdr["t_s"], hdr["update"], hdr["count"] = 0.05, 1, 4
    corners = np.array([[sx * 0.02, sy * 0.02, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    w.add_contacts(hdr, np.zeros((4, 3), dtype=np.int64), corners, np.tile([0.0, 0.0, 1.0], (4, 1)),
                   np.full(4, -0.0002))
    w.add_rows(flat)
    w.close()


def _view(*args) -> tuple[subprocess.Popen, str]:
    view = subprocess.Popen([*HAPTICPROXY, "view", *args, "--port", str(_port()), "--grpc-port", str(_port()),
                             "--duration", "900"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = view.stdout.readline()
    m = re.search(r"open (http://\S+)", line)
    assert m, (line, view.poll(), view.stderr.read() if view.poll() is not None else "")
    return view, m.group(1)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow
@_NEEDS
def test_a_recording_replays_in_3d_in_a_real_browser(tmp_path):
    rec = tmp_path / "run.mcap"
    _recording(rec)
    view, url = _view(str(rec))
    try:
        shot = capture(url, tmp_path / "replay.png", timeout_s=600.0)
    finally:
        _stop(view)
    assert scene_drawn(shot.png)[0]
    assert view.returncode == 0


@pytest.mark.slow
@_NEEDS
def test_the_live_view_draws_a_running_servers_contacts_in_a_real_browser(tmp_path):
    """As the README says: ``serve --config deploy/configs/spatial-pybullet.toml`` (on free ports),
    ``client pybullet --scene loose`` (its 40 mm cube pushed onto the floor by the config's
    hand), ``view --config`` the same file: the page draws the cube and its contacts."""
    if importlib.util.find_spec("pybullet") is None:
        pytest.skip("pybullet is not installed (the engines extra)")
    from hapticproxy.server.status import query

    url = f"udp://127.0.0.1:{_port(socket.SOCK_DGRAM)}"
    status = f"127.0.0.1:{_port(socket.SOCK_DGRAM)}"
    cfg = tmp_path / "spatial-pybullet.toml"
    text = (ROOT / "deploy" / "configs" / "spatial-pybullet.toml").read_text()
    cfg.write_text(text.replace("udp://127.0.0.1:9870", url).replace("127.0.0.1:9871", status))
    procs = [subprocess.Popen([*HAPTICPROXY, "serve", "--config", str(cfg)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)]
    try:
        procs.append(subprocess.Popen(["nice", "-n", "10", *HAPTICPROXY, "client", "pybullet", "--scene", "loose",
                                       "--connect", url, "--connect-timeout", "300", "--duration", "900"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
        t_end = time.monotonic() + 300
        while True:  # the client engaged and resting on the floor
            assert all(p.poll() is None for p in procs), [p.stderr.read() for p in procs if p.poll() is not None]
            try:
                if query(status, timeout_s=0.5).get("contacts", 0) >= 1:
                    break
            except TimeoutError:
                pass
            assert time.monotonic() < t_end, "no contact"
            time.sleep(0.5)
        view, page = _view("--config", str(cfg))
        procs.append(view)
        shot = capture(page, tmp_path / "live.png", timeout_s=600.0)
        assert scene_drawn(shot.png)[0]
    finally:
        for p in reversed(procs):
            _stop(p)
