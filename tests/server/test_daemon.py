"""The daemon in real time: a short run at 1 kHz with a client on loopback that completes without
a fault (counts, never timings), status, clean stop on SIGTERM, telemetry that survives a crash."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from server_harness import WallEnv

from hapticproxy.server import telemetry
from hapticproxy.server.clock import CPU_DMA_LATENCY, MonotonicClock
from hapticproxy.server.shm import NTEL, TEL_FIELDS
from hapticproxy.server.status import query

HAPTICPROXY = [sys.executable, "-m", "hapticproxy.cli.main"]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(tmp_path: Path, extra: str = "", loop: str = "") -> tuple[Path, str, str]:
    url = f"udp://127.0.0.1:{_free_udp_port()}"
    status = f"127.0.0.1:{_free_udp_port()}"
    f = tmp_path / "scene.toml"
    f.write_text(f"""
[loop]
rate_hz = 1000.0
{loop}
[transport]
url = "{url}"
[status]
address = "{status}"
[device]
driver = "sim"
kind = "planar"
watchdog_s = 0.5
hand = {{ type = "constant", wrench = [0.0, -0.5, 0.0] }}
{extra}
""")
    return f, url, status


def _wait_status(address: str, proc, timeout_s: float = 120.0) -> dict:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if proc.poll() is not None:
            raise AssertionError(f"server exited early: {proc.returncode}\n{proc.stderr.read()}")
        try:
            s = query(address, timeout_s=0.5)
            if s.get("ready") == 1.0 and s.get("steps", 0) > 0:
                return s
        except TimeoutError:
            pass
        time.sleep(0.2)
    raise AssertionError("server never answered status")


@pytest.fixture
def server(tmp_path):
    procs = []

    def start(extra: str = "", args=(), loop: str = ""):
        cfg, url, status = _config(tmp_path, extra, loop)
        p = subprocess.Popen(HAPTICPROXY + ["serve", "--config", str(cfg), *args], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        procs.append(p)
        _wait_status(status, p)
        return p, url, status

    yield start
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait(10)


def _drive(env: WallEnv, seconds: float) -> None:
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        env.service()
        time.sleep(0.0005)


def test_real_time_run_with_a_client_completes_without_a_fault(server, tmp_path):
    rec = tmp_path / "run.mcap"
    proc, url, status = server(args=["--record", str(rec)])
    env = WallEnv(url, MonotonicClock(), rate_hz=60.0)
    try:
        _drive(env, 3.0)
        s = query(status)
        assert s["loop_state"] == "engaged"
        assert s["fault"] == 0 and s["faults_total"] == 0
        assert s["steps"] > 1000
        assert s["updates"] >= 60  # a 60 Hz client for about 3 s, minus the handshake
        # every applied update acknowledged: the last perhaps in the step after the snapshot
        assert 0 <= s["updates"] - s["acks_sent"] <= 1
        assert env.proxy_states >= 0.9 * s["updates"]
        assert s["session_id"] != 0 and s["contacts"] >= 1
        assert s["lateness_us"]["count"] == s["steps"] or s["lateness_us"]["count"] >= s["steps"] - 10
        # SIGTERM: ramp down, Bye, flush, exit 0
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
        _drive(env, 0.2)
        assert env.ep.state == "closed" and env.ep.bye is not None
    finally:
        env.close()
    meta, rows = telemetry.read(rec)
    assert meta["fields"] == list(TEL_FIELDS)
    assert rows.shape[1] == NTEL and len(rows) > 1000
    f = {n: i for i, n in enumerate(meta["fields"])}
    assert np.all(np.diff(rows[:, f["t_s"]]) > 0)
    assert abs(rows[-1, f["cmd_fy"]]) < 1e-9  # the recording ends after the ramp-down


def test_status_json_and_rearm_and_stop(server):
    proc, url, status = server()
    out = subprocess.run(HAPTICPROXY + ["status", "--address", status, "--json"], capture_output=True, text=True,
                         timeout=30)
    assert out.returncode == 0, out.stderr
    s = json.loads(out.stdout)
    for key in ("rate_hz", "lateness_us", "overruns", "contacts", "session_id", "watchdog", "rt_scheduling"):
        assert key in s
    assert s["lateness_us"]["p99"] is not None
    # [loop] cpu_latency_us = 0 (the default) held while the loop runs, where the kernel lets it
    held = os.access(CPU_DMA_LATENCY, os.W_OK)
    assert s["cpu_latency_us"] == (0 if held else -1)
    out = subprocess.run(HAPTICPROXY + ["status", "--address", status], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0 and "lateness us" in out.stdout
    assert ("idle CPUs wake within 0 us" if held else "wake-up latency not held") in out.stdout
    # [loop] clock_cpu = "auto": on 2 CPUs or more the clock thread ticks on the highest, the loop's
    # Python thread (its main thread) on the others
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) >= 2:
        assert s["clock_cpu"] == allowed[-1] and f"clock thread on CPU {allowed[-1]}" in out.stdout
        masks = _thread_cpus(int(s["pid"]))
        assert masks[int(s["pid"])] == set(allowed[:-1])
        assert sum(m == {allowed[-1]} for m in masks.values()) == 1  # the clock thread, alone there
    assert query(status, {"cmd": "rearm"})["ok"]
    assert "error" in query(status, {"cmd": "fly"})
    out = subprocess.run(HAPTICPROXY + ["status", "--address", status, "--stop"], capture_output=True, text=True,
                         timeout=30)
    assert out.returncode == 0
    assert proc.wait(30) == 0


def test_status_without_a_server_is_one_line_and_non_zero():
    out = subprocess.run(HAPTICPROXY + ["status", "--address", f"127.0.0.1:{_free_udp_port()}", "--timeout", "0.3"],
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 1
    assert out.stderr.count("\n") == 1 and "no server answering" in out.stderr


@pytest.mark.parametrize("extra, key", [
    ("[controller]\ntype = \"pid\"", "controller.type"),
    ("[safety]\nmax_force_n = -1", "safety.max_force_n"),
])
def test_bad_config_is_refused_with_the_key(tmp_path, extra, key):
    cfg, _, _ = _config(tmp_path, extra)
    out = subprocess.run(HAPTICPROXY + ["serve", "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert key in out.stderr and "Traceback" not in out.stderr


def test_bad_device_table_is_refused_before_start(tmp_path):
    cfg, _, _ = _config(tmp_path)
    cfg.write_text(cfg.read_text().replace("watchdog_s = 0.5", "watchdog_s = 0.5\nmass_kg = -3"))
    out = subprocess.run(HAPTICPROXY + ["serve", "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "device.mass_kg" in out.stderr and "Traceback" not in out.stderr


def test_telemetry_survives_a_crash_of_the_loop_process(server, tmp_path):
    rec = tmp_path / "crash.mcap"
    proc, url, status = server(extra="[telemetry]\nflush_rows = 64", args=["--record", str(rec)])
    time.sleep(1.0)
    s = query(status)
    steps_before = s["steps"]
    os.kill(int(s["pid"]), signal.SIGKILL)  # the loop process dies without any clean-up
    code = proc.wait(30)
    assert code != 0  # the supervisor reports the crash
    meta, rows = telemetry.read(rec)
    assert len(rows) >= steps_before - 64  # everything up to the last flushed block (and more)
    assert meta["torn_bytes"] == 0


def test_torn_last_block_is_ignored(tmp_path):
    from hapticproxy.server.telemetry import TelemetryWriter

    p = tmp_path / "t.hpt"
    w = TelemetryWriter(p, rate_hz=1000.0, flush_rows=10)
    w.add(np.arange(25 * NTEL, dtype=float).reshape(25, NTEL))
    w.close()
    data = p.read_bytes()
    p.write_bytes(data[:-100])  # the last (5-row) block is torn
    meta, rows = telemetry.read(p)
    assert len(rows) == 20 and meta["blocks"] == 2 and meta["torn_bytes"] > 0
    np.testing.assert_array_equal(rows[-1], np.arange(19 * NTEL, 20 * NTEL))


def test_plot_writes_pngs(tmp_path):
    from hapticproxy.server.plot import plot_recording
    from hapticproxy.server.telemetry import TelemetryWriter

    p = tmp_path / "p.hpt"
    w = TelemetryWriter(p, rate_hz=1000.0, flush_rows=100)
    rows = np.zeros((300, NTEL))
    rows[:, 0] = np.arange(300) * 1e-3
    rows[:, TEL_FIELDS.index("dev_qw")] = 1.0
    rows[:, TEL_FIELDS.index("proxy_qw")] = 1.0
    w.add(rows)
    w.close()
    out = plot_recording(p, tmp_path / "png")
    assert len(out) == 4 and all(q.stat().st_size > 1000 for q in out)


def test_the_loop_stops_when_its_supervisor_dies(server):
    proc, url, status = server()
    loop_pid = int(query(status)["pid"])
    proc.kill()  # SIGKILL: the supervisor cannot clean up
    proc.wait(10)
    t_end = time.monotonic() + 20
    alive = True
    while time.monotonic() < t_end and alive:
        try:
            os.kill(loop_pid, 0)
            time.sleep(0.1)
        except ProcessLookupError:
            alive = False
    assert not alive, "the loop process outlived its supervisor"


def _exited(pid: int, timeout_s: float) -> bool:
    """Whether process ``pid`` has exited (gone, or a zombie its new parent has not reaped yet)."""
    t_end = time.monotonic() + timeout_s
    while True:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rpartition(")")[2].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        if time.monotonic() > t_end:
            return False
        time.sleep(0.05)


def _shm_blocks(pid: int) -> set[str]:
    """The POSIX shared-memory blocks process ``pid`` has mapped (names under /dev/shm)."""
    with open(f"/proc/{pid}/maps") as f:
        return {ln.split("/dev/shm/", 1)[1].strip() for ln in f if "/dev/shm/" in ln}


def test_a_supervisor_killed_mid_contact_leaks_no_shared_memory(server):
    """Papercut 6: SIGKILL of the supervisor while a client is in contact. The loop process, now
    the block's last user, stops by itself, unlinks the block and tells Python's resource tracker
    (which the loop shares with its dead supervisor under ``spawn``), so the tracker finds nothing
    to clean up: no 'leaked shared_memory objects' warning, no block left in /dev/shm."""
    proc, url, status = server()
    env = WallEnv(url, MonotonicClock(), rate_hz=60.0)
    try:
        _drive(env, 1.5)
        s = query(status)
        assert s["loop_state"] == "engaged" and s["contacts"] >= 1  # mid-contact
        loop_pid = int(s["pid"])
        blocks = _shm_blocks(loop_pid)
        assert len(blocks) == 1, blocks
        proc.kill()
        # the pipe reaches EOF once every holder is gone: the supervisor, its loop process and
        # the resource tracker (which writes its warning there before it exits)
        _, err = proc.communicate(timeout=60)
    finally:
        env.close()
    assert _exited(loop_pid, 20.0), "the loop process outlived its supervisor"
    assert "leaked" not in err and "resource_tracker" not in err, err
    assert not any(os.path.exists(f"/dev/shm/{b}") for b in blocks), blocks


def test_the_idle_latency_and_the_clock_cpu_can_be_left_to_the_os(server):
    proc, url, status = server(loop='cpu_latency_us = "off"\nclock_cpu = -1')
    s = query(status)
    assert s["cpu_latency_us"] == -1 and s["clock_cpu"] == -1
    out = subprocess.run(HAPTICPROXY + ["status", "--address", status], capture_output=True, text=True, timeout=30)
    assert "wake-up latency not held)" in out.stdout and "clock thread on CPU" not in out.stdout
    allowed = set(os.sched_getaffinity(0))
    assert all(m == allowed for m in _thread_cpus(int(s["pid"])).values())


def _thread_cpus(pid: int) -> dict[int, set[int]]:
    """Each thread of process ``pid``: the CPUs it may run on (/proc's Cpus_allowed_list)."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        for line in Path(f"/proc/{pid}/task/{tid}/status").read_text().splitlines():
            if line.startswith("Cpus_allowed_list:"):
                cpus = set()
                for part in line.split(":", 1)[1].strip().split(","):
                    a, _, b = part.partition("-")
                    cpus |= set(range(int(a), int(b or a) + 1))
                out[int(tid)] = cpus
    return out
