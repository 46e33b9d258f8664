"""Seeing the server: the live view (a real Foxglove WebSocket client receives the advertised
channels and a contact), the terminal view (textual's pilot), the recording's messages and their
schemas, conversion of old and torn recordings, and the status conventions (strict JSON, HMAC,
caller-side dump paths)."""
from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_ws import SUBPROTOCOLS, FoxgloveClient
from server_harness import WallEnv

from hapticproxy.server import config as cfgmod
from hapticproxy.server import recording
from hapticproxy.server.clock import MonotonicClock
from hapticproxy.server.daemon import Supervisor, jsonable
from hapticproxy.server.shm import NTEL, TEL, TEL_DTYPE, SharedState
from hapticproxy.testing.cleanup import made_then_ended

HAPTICPROXY = [sys.executable, "-m", "hapticproxy.cli.main"]


def _port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _settings(kind: str = "planar", **extra):
    url = f"udp://127.0.0.1:{_port()}"
    dev = {"driver": "sim", "kind": kind, "watchdog_s": 0.5,
           "hand": {"type": "constant", "wrench": [0.0, -0.5, 0.0] + ([0.0] * 3 if kind == "spatial" else [])}}
    if kind == "1dof":
        dev.update(axis=[0.0, 1.0, 0.0], hand={"type": "constant", "wrench": [-0.5]})
    d = {"transport": {"url": url}, "status": {"address": f"127.0.0.1:{_port()}"}, "device": dev}
    for k, v in extra.items():
        d.setdefault(k, {}).update(v)
    return cfgmod.load(d)


class Rig:
    """A supervisor (its loop in its own process) and a wall client, both serviced here."""

    def __init__(self, kind="planar", record="", live="", **extra):
        self.settings = _settings(kind, **extra)
        self.sup = Supervisor(self.settings, record=record, live=live)
        self.sup.start()
        self.env = WallEnv(self.settings["transport"]["url"], MonotonicClock(), rate_hz=60.0, kind=kind,
                           start_pose=(0.0, 0.011, 0.0))

    def run(self, seconds: float, until=None) -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            self.env.service()
            self.sup._serve_status(0.0005)
            self.sup.service()
            if until is not None and until():
                return

    def close(self) -> None:
        self.env.close()
        self.sup.close()


@pytest.fixture
def rig():
    yield from made_then_ended(Rig)


# ------------------------------------------------------------------------------ live view
@pytest.mark.parametrize("kind", ["planar", "spatial", "1dof"])
def test_live_view_serves_the_scene_with_a_contact_to_a_foxglove_client(rig, kind):
    r = rig(kind, live=f"127.0.0.1:{_port(socket.SOCK_STREAM)}")
    r.run(30.0, until=lambda: r.sup.shared.get("contacts") > 0)
    assert r.sup.shared.get("contacts") > 0
    host, port = r.sup.live.address.rsplit(":", 1)
    c = FoxgloveClient(host, int(port))
    try:
        assert c.headers.get("sec-websocket-protocol") in SUBPROTOCOLS
        c.sock.settimeout(0.05)
        got: dict = {}

        def pump(until, seconds=15.0):
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                r.run(0.02)
                try:
                    if c.poll(until, timeout_s=0.05):
                        return True
                except (TimeoutError, socket.timeout):
                    pass
            return False

        assert pump(lambda k, m: k == "json" and m.get("op") == "advertise" and len(c.channels) >= 2)
        topics = {ch["topic"]: ch for ch in c.channels.values()}
        assert topics["/scene"]["schemaName"] == "foxglove.SceneUpdate"
        assert json.loads(topics["/live/state"]["schema"])["title"] == "hapticproxy.LiveState"
        c.subscribe("/live/state", 1)
        c.subscribe("/scene", 2)

        def seen(k, m):
            if k == "message":
                got.setdefault(m[0], []).append(m)
            return 1 in got and 2 in got

        assert pump(seen)
        state = json.loads(got[1][-1][2])
        assert state["device_kind"] == kind and state["state"] == "engaged"
        assert len(state["contacts"]) >= 1
        n = state["contacts"][0]["normal"]
        assert n == pytest.approx([0.0, 1.0, 0.0], abs=1e-9)  # the floor's normal
        assert state["force_cap_n"] > 0 and len(state["device_pose"]) == 7
        scene = got[2][-1][2]  # protobuf: the entity ids are plain strings in it
        assert b"device" in scene and b"proxy" in scene and b"contacts" in scene
        assert got[1][-1][1] > 1_000_000_000 * 1_000_000_000  # log time: Unix ns
    finally:
        c.close()


def test_the_live_view_sends_nothing_without_a_subscriber(rig):
    r = rig(live=f"127.0.0.1:{_port(socket.SOCK_STREAM)}")
    r.run(1.0)
    assert r.sup.live.frames == 0


# ------------------------------------------------------------------------------ terminal view
def test_watch_shows_state_pose_force_contacts_and_reason():
    import asyncio

    from hapticproxy.server.watch import WatchApp

    status = {"loop_state": "fault", "fault_name": "speed", "device_fault_name": "ok", "gain": 0.25,
              "last_transition": {"from": "engaged", "to": "fault", "text": "device faster than its limit"},
              "latest": {"device_pose": [0.001, 0.0105, 0.0, 1.0, 0.0, 0.0, 0.0],
                         "proxy_pose": [0.0, 0.0100, 0.0, 1.0, 0.0, 0.0, 0.0],
                         "command": [0.0, -0.5, 0.0, 0.0, 0.0, 0.0]},
              "force_cap_n": 8.0, "torque_cap_n_m": 0.5, "contacts": 2,
              "last_update": {"count": 2, "penetration_m": 0.0004}, "updates": 120, "env_rate_hz": 59.9,
              "lateness_us": {"p50": 1.0, "p99": 4.0, "p999": 40.0}, "compute_us": {"p50": 8.0, "p99": 60.0},
              "rate_hz": 1000.0, "achieved_rate_hz": 999.9, "steps": 5000, "session_id": 7, "device_kind": "planar",
              "energy_hand_j": 0.0123, "tank_j": 0.0042, "passivity_limited": 7}
    sent = []
    calls = {"n": 0}

    def fetch():
        calls["n"] += 1
        if calls["n"] == 3:
            raise TimeoutError("no server answering")
        return status

    async def go():
        app = WatchApp(fetch, send=lambda cmd: sent.append(cmd) or {"ok": True}, interval_s=0.05)
        async with app.run_test(size=(120, 40)) as pilot:
            await pilot.pause(0.3)
            text = {w: app.panel_text(w) for w in ("state", "pose", "force", "contacts", "timing")}
            await pilot.press("r")
            await pilot.pause(0.1)
            misses = app.misses
        return text, misses

    text, misses = asyncio.run(go())
    assert "fault" in text["state"] and "speed" in text["state"] and "device faster than its limit" in text["state"]
    assert "+12.30 mJ given to the hand" in text["state"]  # the ledger at the hand's port
    assert "4.20 mJ, limited 7 steps" in text["state"]  # the passivity layer's tank
    assert "+10.50" in text["pose"] and "+10.00" in text["pose"]  # device / proxy y in mm
    assert "-0.500" in text["force"] and "8.00 N" in text["force"]
    assert "0.400 mm" in text["contacts"]
    assert "p99 4.0" in text["timing"]
    assert sent == ["rearm"]
    assert misses >= 1  # a missed poll is shown, not fatal


def test_watch_dims_every_panel_while_the_server_does_not_answer():
    """Papercut 8: the server goes away; every panel (not just the header) is dimmed and says how
    old its values are; when it answers again they are live again."""
    import asyncio

    from hapticproxy.server.watch import WatchApp

    up = {"on": True}

    def fetch():
        if not up["on"]:
            raise TimeoutError("no server answering on 127.0.0.1:9871")
        return {"loop_state": "stopping", "gain": 0.4, "latest": None}

    async def go():
        app = WatchApp(fetch, interval_s=0.05)
        seen = {}
        async with app.run_test(size=(120, 40)) as pilot:
            await pilot.pause(0.2)
            seen["live"] = [app.query_one(f"#{w}").has_class("stale") for w, _ in app.PANELS]
            up["on"] = False
            await pilot.pause(0.2)
            seen["gone"] = [app.query_one(f"#{w}").has_class("stale") for w, _ in app.PANELS]
            seen["titles"] = [str(app.query_one(f"#{w}").border_title) for w, _ in app.PANELS]
            up["on"] = True
            await pilot.pause(0.2)
            seen["back"] = [app.query_one(f"#{w}").has_class("stale") for w, _ in app.PANELS]
        return seen

    seen = asyncio.run(go())
    assert seen["live"] == [False] * 5 and seen["gone"] == [True] * 5 and seen["back"] == [False] * 5
    assert all("stale: last answer" in t for t in seen["titles"]), seen["titles"]


def test_watch_against_a_real_server(rig):
    import asyncio

    from hapticproxy.server.status import query
    from hapticproxy.server.watch import WatchApp

    r = rig()
    r.run(30.0, until=lambda: r.sup.shared.get("contacts") > 0)
    addr = r.settings["status"]["address"]
    import threading

    stop = threading.Event()
    th = threading.Thread(target=lambda: [r.run(0.05) for _ in iter(stop.is_set, True)], daemon=True)
    th.start()
    try:
        async def go():
            app = WatchApp(lambda: query(addr, timeout_s=1.0), interval_s=0.1)
            async with app.run_test(size=(120, 40)) as pilot:
                await pilot.pause(0.5)
                return app.panel_text("state"), app.panel_text("contacts")

        state, contacts = asyncio.run(go())
    finally:
        stop.set()
        th.join(5)
    assert "engaged" in state and "session" in state
    assert "contacts" in contacts and "deepest" in contacts


# ------------------------------------------------------------------------------ recordings
def test_recording_holds_every_step_contact_update_and_transition(rig, tmp_path):
    path = tmp_path / "run.mcap"
    r = rig(record=str(path), telemetry={"flush_rows": 256})
    r.run(30.0, until=lambda: r.sup.shared.get("updates") > 60)
    r.sup.request_stop()
    r.run(3.0, until=lambda: not r.sup.proc.is_alive())
    head, updates = int(r.sup.shared.head[0]), int(r.sup.shared.get("updates"))
    start = r.sup.writer._read - (r.sup.writer.rows_written + r.sup.writer._pending)
    r.close()
    rec = recording.read(path)
    assert rec.torn_bytes == 0 and rec.meta["format"] == recording.FORMAT
    assert rec.meta["device_kind"] == "planar" and rec.meta["config"]["device"]["kind"] == "planar"
    assert len(rec.tel) == head - start  # every step from the start of the recording
    assert np.all(np.diff(rec.tel["t_s"]) > 0)
    assert len(rec.contacts) == updates  # every applied update (the recording started before the first)
    assert all(c["count"] == len(c["key"]) for c in rec.contacts)
    assert rec.contacts[-1]["normal"][0] == pytest.approx([0.0, 1.0, 0.0])
    names = [(tr.from_state, tr.to_state) for tr in rec.transitions]
    assert ("idle", "engaged") in names and names[-1] == ("stopping", "stopped")
    assert rec.transitions[1].reason == "engage"


def test_every_schema_is_plain_json_schema_and_matches_its_messages(tmp_path):
    """Foxglove parses plain JSON schemas (objects inlined, no $ref, typed fields); every field of
    every message is in its schema with its JSON type."""
    sh = SharedState.local(64)
    sh.ring[:40] = np.random.default_rng(0).normal(size=(40, NTEL))
    sh.ring[:40, TEL["t_s"]] = np.arange(40) * 1e-3
    for c in ("loop_state", "contacts", "updates"):  # integers in the recording
        sh.ring[:40, TEL[c]] = np.arange(40) % 5
    sh.ring[5, TEL["hand_fx"]] = np.nan
    sh.ring[:40, TEL["seq"]] = np.arange(40)  # each row complete (the ring's seqlock: its number)
    sh.head[0] = 40
    p = tmp_path / "s.mcap"
    recording.dump_ring(sh, p, rate_hz=1000.0)
    from mcap.reader import make_reader

    types = {"number": (int, float, type(None)), "integer": (int,), "string": (str,), "array": (list,),
             "object": (dict,)}

    def check(schema, value):
        assert "$ref" not in schema and "anyOf" not in schema
        assert isinstance(value, types[schema["type"]]), (schema, value)
        if schema["type"] == "object":
            assert set(value) == set(schema["properties"])
            for k, v in value.items():
                check(schema["properties"][k], v)
        elif schema["type"] == "array":
            for v in value:
                check(schema["items"], v)

    seen = set()
    with open(p, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            seen.add(channel.topic)
            if channel.topic in recording.SCENE_TOPICS:
                continue  # Foxglove's own protobuf schemas (test_recording_carries_the_3d_scene...)
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            check(json.loads(schema.data), json.loads(message.data))
    assert seen == set(recording.STEP_TOPICS) | set(recording.SCENE_TOPICS)
    rows = recording.read(p).rows
    np.testing.assert_array_equal(rows, sh.ring[:40])  # NaN (null) and all


def test_the_fast_step_encoder_writes_what_the_structs_encode():
    import msgspec

    rows = np.random.default_rng(1).normal(size=(50, NTEL)) * 10.0 ** np.random.default_rng(2).integers(-9, 4, NTEL)
    for c in ("loop_state", "contacts", "updates"):
        rows[:, TEL[c]] = np.arange(50) % 7
    rows[3, TEL["env_fy"]] = np.inf
    rows[4, TEL["updates"]] = np.nan
    enc = msgspec.json.Encoder()
    fast = recording.StepEncoder().encode(rows)
    for k in range(50):
        assert fast[k][1] == [enc.encode(m) for m in recording.step_messages(rows[k].tolist())]


def test_a_torn_recording_reads_to_its_last_chunk_and_converts_whole(tmp_path):
    sh = SharedState.local(4096)
    sh.ring[:3000] = 0.0
    sh.ring[:3000, TEL["t_s"]] = np.arange(3000) * 1e-3
    sh.ring[:3000, TEL["seq"]] = np.arange(3000)  # each row complete (the ring's seqlock: its number)
    sh.head[0] = 3000
    p = tmp_path / "t.mcap"
    w = recording.McapRecorder(p, rate_hz=1000.0, flush_rows=1000)
    sh.head[0] = 2000
    w.drain(sh)
    at_crash = p.read_bytes()  # what a crash leaves now: two chunks on disk, no summary
    sh.head[0] = 3000
    w.drain(sh)
    w.close()
    data = p.read_bytes()
    rec = recording.read(p)
    assert len(rec.tel) == 3000 and rec.torn_bytes == 0 and rec.chunks == 3
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(at_crash + data[len(at_crash):len(at_crash) + 50])  # and half a record of the third
    rec = recording.read(torn)
    assert len(rec.tel) == 2000 and rec.torn_bytes == 50
    out = subprocess.run(HAPTICPROXY + ["convert", str(torn), str(tmp_path / "fixed.mcap")], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    from mcap.reader import make_reader

    with open(tmp_path / "fixed.mcap", "rb") as f:
        summary = make_reader(f).get_summary()  # what PlotJuggler reads first
    assert summary is not None
    counts = summary.statistics.channel_message_counts
    assert sum(n for cid, n in counts.items() if summary.channels[cid].topic in recording.STEP_TOPICS) == \
        2000 * len(recording.STEP_TOPICS)
    assert sum(n for cid, n in counts.items() if summary.channels[cid].topic == "/scene") in (59, 60)  # 2 s at 30 Hz


def test_an_old_hpt_recording_converts_and_plots(tmp_path):
    from hapticproxy.server.telemetry import TelemetryWriter

    p = tmp_path / "old.hpt"
    w = TelemetryWriter(p, rate_hz=1000.0, config={"device": {"kind": "planar"}}, flush_rows=100)
    rows = np.zeros((300, NTEL))
    rows[:, TEL["t_s"]] = np.arange(300) * 1e-3
    rows[:, TEL["dev_qw"]] = rows[:, TEL["proxy_qw"]] = 1.0
    rows[:, TEL["cmd_fy"]] = -0.5
    rows[:, TEL["seq"]] = np.arange(300)  # as the loop numbers its rows
    w.add(rows)
    w.close()
    out = subprocess.run(HAPTICPROXY + ["convert", str(p), str(tmp_path / "new.mcap")], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    rec = recording.read(tmp_path / "new.mcap")
    np.testing.assert_array_equal(rec.rows, rows)
    out = subprocess.run(HAPTICPROXY + ["plot", str(tmp_path / "new.mcap"), "--out", str(tmp_path / "png")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert len(list((tmp_path / "png").glob("new_*.png"))) == 4


# ------------------------------------------------------------------------------ plot
def test_plot_spans_noise_and_keeps_the_command_in_view(tmp_path):
    """A 1e-13 deg rotation noise stays a flat line; a spike in the model's force does not set
    the force axis; a spatial run gets all six axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.figure

    from hapticproxy.server import plot

    n = 500
    tel = np.zeros(n, TEL_DTYPE)
    flat = tel.view(np.float64).reshape(n, NTEL)
    flat[:, TEL["t_s"]] = np.arange(n) * 1e-3
    flat[:, TEL["dev_qw"]] = flat[:, TEL["proxy_qw"]] = 1.0
    ang = np.radians(1e-13) * np.sin(np.arange(n))
    flat[:, TEL["dev_qw"]], flat[:, TEL["dev_qx"]] = np.cos(ang / 2), np.sin(ang / 2)
    flat[:, TEL["cmd_fz"]] = np.linspace(0.0, 0.5, n)
    flat[:, TEL["env_fz"]] = 0.5
    flat[250, TEL["env_fz"]] = 400.0  # a spike in the model's force
    p = tmp_path / "sp.mcap"
    w = recording.McapRecorder(p, rate_hz=1000.0, config={"device": {"kind": "spatial"}},
                               meta={"device_kind": "spatial", "force_cap_n": 8.0, "torque_cap_n_m": 0.5})
    w.add_rows(tel)
    w.close()
    captured = {}
    real_savefig = matplotlib.figure.Figure.savefig

    def spy(fig, fname, *a, **kw):
        captured[Path(fname).stem] = [(ax.get_ylabel(), ax.get_ylim()) for ax in fig.axes]
        return real_savefig(fig, fname, *a, **kw)

    matplotlib.figure.Figure.savefig = spy
    try:
        files = plot.plot_recording(p, tmp_path)
    finally:
        matplotlib.figure.Figure.savefig = real_savefig
    assert len(files) == 4
    traj = dict(captured["sp_trajectory"])
    assert set(traj) == {"x [mm]", "y [mm]", "z [mm]", "rotation about x [deg]", "rotation about y [deg]",
                         "rotation about z [deg]"}
    lo, hi = traj["rotation about x [deg]"]
    assert hi - lo >= plot.MIN_SPAN["deg"]
    forces = dict(captured["sp_forces"])
    lo, hi = forces["fz [N]"]
    assert hi < 20.0 and hi >= 0.5  # the command (and the cap) set the axis, not the 400 N spike


# ------------------------------------------------------------------------------ status conventions
def test_jsonable_is_strict():
    out = json.dumps(jsonable({"a": float("nan"), "b": np.int64(3), "c": [np.float64(1.5), math.inf]}),
                     allow_nan=False)
    assert json.loads(out) == {"a": None, "b": 3, "c": [1.5, None]}


def test_status_json_is_strict_with_integers_and_nulls(rig):
    r = rig()
    r.run(1.0)
    import threading

    stop = threading.Event()
    th = threading.Thread(target=lambda: [r.run(0.05) for _ in iter(stop.is_set, True)], daemon=True)
    th.start()
    try:
        out = subprocess.run(HAPTICPROXY + ["status", "--address", r.settings["status"]["address"], "--json"],
                             capture_output=True, text=True, timeout=60)
    finally:
        stop.set()
        th.join(5)
    assert out.returncode == 0, out.stderr
    assert "NaN" not in out.stdout and "Infinity" not in out.stdout
    s = json.loads(out.stdout)
    for k in ("steps", "updates", "overruns", "session_id", "contacts", "fault", "pid"):
        assert type(s[k]) is int, k
    assert type(s["gain"]) is float and s["loop_state"] in ("idle", "engaged")
    assert s["latest"]["device_pose"] and s["last_transition"]["to"] in ("idle", "engaged")


def test_status_to_a_closed_pipe_leaves_no_traceback(rig):
    r = rig()
    import threading

    stop = threading.Event()
    th = threading.Thread(target=lambda: [r.run(0.05) for _ in iter(stop.is_set, True)], daemon=True)
    th.start()
    try:
        out = subprocess.run(f"{sys.executable} -m hapticproxy.cli.main status --address "
                             f"{r.settings['status']['address']} --json | head -c 10", shell=True,
                             capture_output=True, text=True, timeout=60)
    finally:
        stop.set()
        th.join(5)
    assert "Traceback" not in out.stderr and "BrokenPipe" not in out.stderr, out.stderr


def test_dump_takes_an_absolute_path_and_creates_no_directory(rig, tmp_path):
    from hapticproxy.server.status import query

    r = rig()
    r.run(1.0)
    addr = r.settings["status"]["address"]
    sup = r.sup
    assert "absolute" in sup.handle({"cmd": "dump", "path": "rel.mcap"})["error"]
    assert "does not exist" in sup.handle({"cmd": "dump", "path": str(tmp_path / "no" / "x.mcap")})["error"]
    assert not (tmp_path / "no").exists()
    import threading

    stop = threading.Event()
    th = threading.Thread(target=lambda: [r.run(0.05) for _ in iter(stop.is_set, True)], daemon=True)
    th.start()
    try:
        # the command line resolves a relative path on the caller's side
        out = subprocess.run(HAPTICPROXY + ["status", "--address", addr, "--dump", "d.mcap"], cwd=tmp_path,
                             capture_output=True, text=True, timeout=60)
        del query
    finally:
        stop.set()
        th.join(5)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("wrote ") and out.stdout.rstrip().endswith(f"telemetry rows to {tmp_path / 'd.mcap'}")
    assert len(recording.read(tmp_path / "d.mcap").tel) > 100


def test_requests_are_refused_without_the_hmac_key(rig, tmp_path):
    from hapticproxy.server.status import query, sign

    key = tmp_path / "key.hex"
    key.write_text(os.urandom(32).hex() + "\n")
    key.chmod(0o600)
    r = rig(transport={"hmac_key_file": str(key)})
    addr = r.settings["status"]["address"]
    k = bytes.fromhex(key.read_text().strip())
    results = {}
    import threading

    stop = threading.Event()
    th = threading.Thread(target=lambda: [r.run(0.02) for _ in iter(stop.is_set, True)], daemon=True)
    th.start()
    try:
        results["plain"] = query(addr, {"cmd": "stop"})
        results["bad"] = query(addr, {"cmd": "stop"}, key=b"x" * 32)
        signed = sign({"cmd": "status"}, k)
        results["signed"] = query(addr, signed)
        results["replay"] = query(addr, signed)
        results["old"] = query(addr, dict(sign({"cmd": "status"}, k)))
        stale = {"cmd": "status", "ts": time.time() - 120, "nonce": "n1"}
        from hapticproxy.server.status import request_mac

        stale["mac"] = request_mac(k, stale)
        results["stale"] = query(addr, stale)
        out = subprocess.run(HAPTICPROXY + ["status", "--address", addr, "--key-file", str(key), "--json"],
                             capture_output=True, text=True, timeout=60)
    finally:
        stop.set()
        th.join(5)
    assert "unauthenticated" in results["plain"]["error"]
    assert "bad MAC" in results["bad"]["error"]
    assert results["signed"]["authenticated"] is True and "error" not in results["signed"]
    assert "replayed" in results["replay"]["error"]
    assert "window" in results["stale"]["error"]
    assert r.sup.proc.is_alive() and not r.sup._stop_requested  # the unsigned stop did nothing
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["loop_state"] in ("idle", "engaged")


# ------------------------------------------------------------------------------ the 3-D scene (issue 32)
def test_recording_carries_the_3d_scene_in_standard_schemas(tmp_path):
    """Beside the hapticproxy.* topics a recording holds /tf, /device/pose, /proxy/pose and
    /scene in Foxglove's schemas (protobuf), at 30 Hz, the MCAP header's profile set; each /scene
    message is byte for byte the scene of its row with the contacts applied by then (a contact
    update later than the row is not drawn early)."""
    from mcap.reader import make_reader

    from hapticproxy.server import scene

    n = 1000  # 1 s at 1 kHz
    flat = np.zeros((n, NTEL))
    flat[:, TEL["t_s"]] = np.arange(n) * 1e-3
    flat[:, TEL["dev_x"]] = np.linspace(0.0, 0.01, n)
    flat[:, TEL["proxy_x"]] = np.linspace(0.0, 0.009, n)
    flat[:, TEL["proxy_z"]] = 0.02
    flat[:, TEL["dev_qw"]] = flat[:, TEL["proxy_qw"]] = 1.0
    flat[:, TEL["cmd_fz"]] = -0.5
    flat[:, TEL["env_fz"]] = 0.5
    flat[:, TEL["loop_state"]] = 2
    flat[:, TEL["gain"]] = 1.0
    hdr = np.zeros((), dtype=[("t_s", "f8"), ("env_time_s", "f8"), ("update", "i8"), ("count", "i8")])
    p = tmp_path / "scene.mcap"
    w = recording.McapRecorder(p, rate_hz=1000.0, config={"device": {"kind": "spatial"}}, t0_epoch_ns=10**18,
                               meta={"tool_kind": "spatial"})
    shape = scene.ToolShape.from_hello("spatial", 0.2, (0, 0, 0), (0.2 * 0.0032 / 12,) * 3 + (0, 0, 0))
    w.set_shape(shape)
    contacts = []
    for k, t in enumerate((0.1, 0.5)):
        pos = np.array([[0.02 * k, 0.0, 0.0], [0.02 * k, 0.04, 0.0]])
        nrm = np.array([[0.0, 0.0, 1.0]] * 2)
        sep = np.array([-0.001, -0.002 * (k + 1)])
        hdr["t_s"], hdr["update"], hdr["count"] = t, k + 1, 2
        w.add_contacts(hdr, np.zeros((2, 3), dtype=np.int64), pos, nrm, sep)
        contacts.append((t, (pos, nrm, sep)))
    w.add_rows(flat)
    w.close()
    assert w.scenes_written == 30
    with open(p, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "hapticproxy"
        by_topic: dict = {}
        for schema, channel, message in reader.iter_messages(topics=list(recording.SCENE_TOPICS)):
            by_topic.setdefault(channel.topic, []).append((schema.name, channel.message_encoding, message))
    assert {t: {m[0] for m in ms} for t, ms in by_topic.items()} == {
        "/tf": {"foxglove.FrameTransforms"}, "/device/pose": {"foxglove.PoseInFrame"},
        "/proxy/pose": {"foxglove.PoseInFrame"}, "/scene": {"foxglove.SceneUpdate"}}
    assert all(enc == "protobuf" for ms in by_topic.values() for _, enc, _ in ms)
    scenes = by_topic["/scene"]
    assert len(scenes) == 30
    for _, _, m in scenes:
        t = (m.log_time - 10**18) * 1e-9
        i = int(round(t * 1e3))
        applied = [c for tc, c in contacts if tc <= flat[i, TEL["t_s"]]]
        frame = recording.scene_frame(flat[i], applied[-1] if applied else None)
        assert m.data == scene.foxglove_scene(frame, shape, m.log_time).encode(), t
        assert len(frame.separation) == (0 if t < 0.1 else 2)
    # the recording still reads as before: every row
    assert len(recording.read(p).rows) == n


def test_the_tool_shape_from_a_hello_is_its_box():
    from hapticproxy.server.scene import ToolShape

    m, a, b, c = 0.3, 0.08, 0.02, 0.04
    inertia = (m * (b * b + c * c) / 12, m * (a * a + c * c) / 12, m * (a * a + b * b) / 12, 0, 0, 0)
    shape = ToolShape.from_hello("spatial", m, (0.0, 0.01, 0.0), inertia)
    (centre, q, size), = shape.boxes
    assert shape.source == "hello" and centre == (0.0, 0.01, 0.0)
    np.testing.assert_allclose(size, (a, b, c), rtol=1e-12)
    planar = ToolShape.from_hello("planar", m, (0, 0, 0), (0, 0, m * (a * a + b * b) / 12, 0, 0, 0))
    side = planar.boxes[0][2][0]
    assert planar.source == "hello" and abs(m * 2 * side * side / 12 - m * (a * a + b * b) / 12) < 1e-15
    assert ToolShape.from_hello("1dof", m, (0, 0, 0), (0,) * 6).source == "kind"
    assert ToolShape.from_hello("spatial", m, (0, 0, 0), (0,) * 6).source == "kind"


def test_a_recordings_caps_are_the_loops_published_ones_not_a_fresh_blocks_zeros(tmp_path):
    """Issue 28: the recording started as the loop became ready, before its first published
    status, and its metadata said the torque cap was 0.0 N m (the block's zero) where `status`
    said 0.5. The metadata now waits for the loop's first publish (or says null)."""
    from hapticproxy.server.shm import ST

    settings = cfgmod.load(None, {"transport": {"url": "udp://127.0.0.1:0"}, "status": {"address": "127.0.0.1:0"}})
    sup = Supervisor(settings)
    try:
        st = sup.shared.status
        st[ST["force_cap_n"]] = 10.0          # written by the loop when it is built
        st[ST["rate_limit_n_per_step"]] = 1.0
        st[ST["t_start_ns"]] = 1               # ready, not yet published: torque cap still 0
        sup.start_recording(str(tmp_path / "a.mcap"))
        sup.service()
        st[ST["torque_cap_n_m"]] = 0.5         # the loop's first publish
        st[ST["t_last_ns"]] = 2
        sup.service()
    finally:
        sup.close()
    meta = recording.read(tmp_path / "a.mcap").meta
    assert (meta["force_cap_n"], meta["torque_cap_n_m"], meta["rate_limit_n_per_step"]) == (10.0, 0.5, 1.0)

    sup = Supervisor(settings)  # a loop that never published: the caps are unknown, not zero
    try:
        sup.shared.status[ST["force_cap_n"]] = 10.0
        sup.start_recording(str(tmp_path / "b.mcap"))
        sup.service()
    finally:
        sup.close()
    meta = recording.read(tmp_path / "b.mcap").meta
    assert meta["torque_cap_n_m"] is None and meta["force_cap_n"] is None


def test_the_engaged_tool_reaches_the_supervisor_through_the_shared_block(rig, tmp_path):
    """The loop writes the engaged client's tool (its Hello's kind, mass, centre of mass and
    inertia) into the shared status block; the supervisor draws the proxy with that box, and a
    dump of the rings keeps it for a replay."""
    from hapticproxy.server.scene import ToolShape

    r = rig("spatial")
    assert r.sup.status()["tool_shape"] is None  # nothing engaged yet
    r.run(20.0, until=lambda: r.sup.tool_shape is not None)
    hello = r.env.hello
    want = ToolShape.from_hello("spatial", hello.mass_kg, hello.com_m, hello.inertia_kg_m2)
    s = r.sup.status()
    assert s["tool_shape_source"] == "hello" and s["loop_state"] == "engaged"
    assert s["tool_shape"] == [[list(c), list(q), list(z)] for c, q, z in want.boxes]
    assert s["tool_kind"] == "spatial" and s["tool_seq"] == 1  # the first engagement
    assert r.sup.handle({"cmd": "dump", "path": str(tmp_path / "dump.mcap")})["ok"]
    assert recording.read(tmp_path / "dump.mcap").meta["tool_shape"]["boxes"] == s["tool_shape"]


def test_the_supervisor_reads_each_engaged_tool_once_and_never_one_half_written():
    """``publish_tool`` numbers each engaged tool; ``tool_seq`` is -1 while the fields change, so
    the supervisor keeps the shape it had; a new number is a new shape (the same number again is
    not read twice)."""
    from hapticproxy.server.scene import ToolShape
    from hapticproxy.server.shm import ST

    settings = cfgmod.load(None, {"transport": {"url": "udp://127.0.0.1:0"}, "status": {"address": "127.0.0.1:0"}})
    sup = Supervisor(settings)
    try:
        sh = sup.shared
        assert sh.engaged_tool() is None
        box = (2e-4, 3e-4, 4e-4, 0.0, 0.0, 0.0)
        sh.publish_tool(1, 3, 0.2, (0.0, 0.01, 0.0), box)
        assert sh.engaged_tool() == (1, 3, 0.2, (0.0, 0.01, 0.0), box)
        sup.service()
        first = ToolShape.from_hello("spatial", 0.2, (0.0, 0.01, 0.0), box)
        assert sup.tool_shape.boxes == first.boxes and sup.tool_shape.source == "hello"
        sh.status[ST["tool_seq"]] = -1.0  # the loop is writing the next one
        sh.status[ST["tool_mass_kg"]] = 0.4
        assert sh.engaged_tool() is None
        sup.service()
        assert sup.tool_shape.boxes == first.boxes
        sh.status[ST["tool_seq"]] = 1.0  # the same number: not read again
        sup.service()
        assert sup.tool_shape.boxes == first.boxes
        sh.publish_tool(2, 2, 0.1, (0.0, 0.0, 0.0), (0.0, 0.0, 1e-4, 0.0, 0.0, 0.0))
        sup.service()
        assert sup.tool_shape.boxes == ToolShape.from_hello("planar", 0.1, (0, 0, 0), (0, 0, 1e-4, 0, 0, 0)).boxes
    finally:
        sup.close()


def test_a_replay_draws_the_proxy_as_the_recorded_tool_not_the_kinds(tmp_path):
    """``set_shape`` (a client engaged) leaves a metadata record in the file; ``hapticproxy view
    FILE.mcap`` draws the proxy with the last one, as the live view did, not the kind's cube."""
    from hapticproxy.cli.view import recording_frames
    from hapticproxy.server.scene import ToolShape

    def record(path, shapes):
        flat = np.zeros((100, NTEL))
        flat[:, TEL["t_s"]] = np.arange(100) * 1e-3
        flat[:, TEL["dev_qw"]] = flat[:, TEL["proxy_qw"]] = 1.0
        w = recording.McapRecorder(path, rate_hz=1000.0, config={"device": {"kind": "spatial"}},
                                   t0_epoch_ns=10**18, meta={"tool_kind": "spatial"})
        for shape in shapes:
            w.set_shape(shape)
        w.add_rows(flat)
        w.close()

    inertia = (2e-5, 5e-5, 6e-5, 0.0, 0.0, 0.0)
    first = ToolShape.from_hello("spatial", 0.2, (0.0, 0.0, 0.0), inertia)
    second = ToolShape.from_hello("spatial", 0.3, (0.0, 0.01, 0.0), inertia)
    record(tmp_path / "two.mcap", [first, second])
    rec = recording.read(tmp_path / "two.mcap")
    assert rec.meta["tool_shape"]["source"] == "hello"
    shape, frames = recording_frames(tmp_path / "two.mcap")
    assert shape.source == "hello" and frames
    np.testing.assert_allclose(np.array(shape.boxes[0][2]), second.boxes[0][2], rtol=1e-12)
    np.testing.assert_allclose(shape.boxes[0][0], (0.0, 0.01, 0.0))
    w = recording.McapRecorder(tmp_path / "late.mcap", rate_hz=1000.0, config={"device": {"kind": "spatial"}},
                               t0_epoch_ns=10**18, meta={"tool_kind": "spatial"}, shape=first)  # engaged before
    w.close()
    assert recording.read(tmp_path / "late.mcap").meta["tool_shape"]["boxes"][0][2] == list(first.boxes[0][2])
    record(tmp_path / "none.mcap", [])  # no client engaged: the kind's shape
    shape, _ = recording_frames(tmp_path / "none.mcap")
    assert shape.source == "kind" and shape.boxes == ToolShape.for_kind("spatial").boxes


def test_the_hand_ports_ledger_reaches_the_loop_topic_and_the_3d_views_label(tmp_path):
    """The energy given to the hand (``energy_hand_j``, the ledger at the device's port) is in
    every /loop message of a recording, reads back as its column, and labels the 3-D scene of a
    recording and of a live status reply alike."""
    from mcap.reader import make_reader

    from hapticproxy.cli.view import frame_from_status

    n = 300
    flat = np.zeros((n, NTEL))
    flat[:, TEL["t_s"]] = np.arange(n) * 1e-3
    flat[:, TEL["dev_qw"]] = flat[:, TEL["proxy_qw"]] = 1.0
    flat[:, TEL["energy_hand_j"]] = np.linspace(0.0, 0.0125, n)
    p = tmp_path / "ledger.mcap"
    w = recording.McapRecorder(p, rate_hz=1000.0, config={"device": {"kind": "planar"}}, t0_epoch_ns=10**18,
                               meta={"tool_kind": "planar"})
    w.add_rows(flat)
    w.close()
    with open(p, "rb") as f:
        got = [json.loads(m.data)["energy_hand_j"] for _, _, m in make_reader(f).iter_messages(topics=["/loop"])]
    assert got == pytest.approx(flat[:, TEL["energy_hand_j"]].tolist())
    assert recording.read(p).rows[:, TEL["energy_hand_j"]] == pytest.approx(flat[:, TEL["energy_hand_j"]])
    assert "hand +12.5 mJ" in recording.scene_frame(flat[-1]).label
    live = {"loop_state": "engaged", "gain": 1.0, "energy_hand_j": -0.002,
            "latest": {"t_s": 1.0, "device_pose": [0, 0, 0, 1, 0, 0, 0], "proxy_pose": [0, 0, 0, 1, 0, 0, 0],
                       "command": [0.0] * 6, "environment_wrench": [0.0] * 6}}
    assert "hand -2.0 mJ" in frame_from_status(live).label
    live.pop("energy_hand_j")  # an older server: no ledger, no number
    assert "mJ" not in frame_from_status(live).label
