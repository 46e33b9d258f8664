"""``hapticproxy bench faults``: the safety promises measured under injected faults.

Every case runs the real server (supervisor + haptic-loop process, 1 kHz, the default controller,
model and ``[safety]`` settings: 10 N cap, 1000 N/s, watchdog 100 ms, fade 200 ms, ramp-in 0.5 s)
with the simulated planar device whose hand pushes the paper's peg onto the testbed's bottom wall
(0.5 N along +y; the wall is met at y_COM = 124 mm) and the pymunk testbed client (``--engine
stub`` for the analytic one) on loopback. Faults are injected in user space (no ``tc netem``):

- **UDP matrix** through :class:`~hapticproxy.testing.impair.ImpairingRelay`, both
  directions impaired with their own seeds: loss 0 / 5 / 30 % uniform and bursty
  (Gilbert-Elliott, mean burst 3 datagrams), delay 20 / 100 ms one way, jitter 50 ms (delay
  50 +- 50 ms), duplication 1 %, reordering 25 %, corruption 1 %, and all of them at once;
- **events**: the environment silent for 400 ms (the relay drops everything client -> server,
  then the session resumes), the client killed mid-contact (SIGKILL of a ``hapticproxy client``
  process), the client saying ``Bye`` mid-contact, the server loop stalled for 100 ms (SIGSTOP /
  SIGCONT of the loop process, with the device in its own process on the remote-device link: its
  watchdog must cut the output and keep it off until ``status --rearm``), and the loop process
  killed (SIGKILL: the device's watchdog cuts the output; the telemetry recording keeps every
  flushed block);
- **the safety filter and the fault policy** (``faults_safety``: its docstring): torque caps and
  rate on a spatial device, the norm cap on a diagonal (spatial, and a 1-DOF device on a diagonal
  axis), the fade envelope under a pushing hand, a device fault 5 s after a recovered stall,
  the handle thrown while idle, flipped normals under a pushing hand, and ``accurate`` (4 kHz)
  on a loaded machine;
- **Zenoh**: the same client over Zenoh through
  :class:`~hapticproxy.testing.impair_tcp.ImpairingTcpProxy` (TCP delay 20 / 100 ms,
  a 400 ms stall, the link reset) and with the messages impaired by
  :class:`~hapticproxy.testing.impair.ImpairedTransport` (30 % bursty loss +
  1 % duplication + 25 % reordering), and a Zenoh client killed mid-contact.

One JSON row per case (``--json``: JSON lines; otherwise a table): ``case``, ``max_force_n``
(largest force component commanded to the device), ``max_force_step_n`` (largest change of a
force component in one haptic step, the fault policy's cut to zero excepted: ``max_cut_n`` is the
largest force a cut removed at once), ``force_cap_n``, ``rate_limit_n_per_step``, ``fade_ms``
(longest fade from its start to zero force, where a fade happened), ``unstable``, ``violations``
(steps that broke a promise) and ``broken`` (which promises, with counts), plus details:
``zero_ms`` (device cut by its own watchdog, from the stall / kill), ``detect_ms`` (environment
silent -> fade starts), ``first_after_ramp_n`` (largest first command after a ramp-in from zero),
``fades``, ``ramps``, ``faults``, ``updates``, ``missed_deadlines``, ``telemetry_rows_lost``.

Promises checked at every step of the server's telemetry (``cmd_*`` = the wrench written to the
device): finite; each force component within the cap (torques within theirs); no component
changing by more than the rate limit per step; within the fade/ramp envelope ``gain * cap``; the
environment silent for longer than the watchdog (+1 step) -> not engaged any more; a fade reaching
zero force within the fade time (+1 step); the first command of a ramp-in from zero at most
``FIRST_COMMAND_MAX_N`` (0.2 N). For the stall and the crash, what the *device* rendered (its own
record): no tick renders force with its last accepted command older than its watchdog (50 ms),
nothing from that cut until the server re-arms, the first command after the re-arm at most 0.2
N, never above the cap (``zero_ms``: from the stop to the cut, including the device's tick).

``unstable``: a speed trip, a force at the cap, or, over the last second before the fault (or of
the run) and from ``FULL_GAIN_SETTLE_S`` after the output last was below full gain, a force
swinging by more than 1 N or a device moving back by more than 1 mm against its net motion while
engaged at full gain (``settle_retrace_mm``: an oscillation; the static-contact experiment's
settle test). A monotone approach to rest is not one: after a ramp-in that a pushing hand rode
deep into the wall, the index offset returns to where the wall was first felt at a limited
speed, which takes longer the deeper the hand went (``settle_ptp_mm`` reports that travel).
"""
from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..protocol.logs import doc_summary
from ..testing.impair import Decision, GilbertElliott, Impairment, ImpairingRelay
from ..protocol.jsonout import print_json

PUSH_N = 0.5
RATE_HZ = 1000.0
#: The device's viscous damping [N s/m]: the 0.5 N push reaches the wall at about 0.05 m/s, as in
#: the client-vs-server tests (with the sim default of 2 N s/m the peg arrives at 0.25 m/s).
DEVICE_DAMPING = 10.0
DEVICE_WATCHDOG_S = 0.05
WORKSPACE = ([-0.25, -0.25], [0.25, 0.25])
#: the settle test starts this long [s] after the output was last below full gain (a ramp-in
#: re-indexes, and the deformation recovers at [model] recovery_speed_m_per_s afterwards)
FULL_GAIN_SETTLE_S = 0.3
SETTLE_S = 3.0  # the hand has pushed the peg onto the wall and it rests there by then
AFTER_S = 1.5   # observed after a fault
SILENT_S = 0.4  # silence / link stall: past the watchdog (0.1 s) and a whole fade (0.2 s)
TOL = 1e-9


def _port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _bursty(mean_loss: float, mean_burst: float = 3.0) -> GilbertElliott:
    """Gilbert-Elliott chain with this stationary loss and mean burst length (datagrams)."""
    p_bg = 1.0 / mean_burst
    p_gb = mean_loss * p_bg / (1.0 - mean_loss)
    return GilbertElliott(p_good_to_bad=p_gb, p_bad_to_good=p_bg)


@dataclass
class Case:
    name: str
    kind: str = "run"              # run | silent | kill | bye | stall | crash
    transport: str = "udp"         # udp | zenoh
    c2s: dict = field(default_factory=dict)   # Impairment kwargs, client -> server
    s2c: dict = field(default_factory=dict)
    tcp_delay_s: float = 0.0       # zenoh: one-way delay of the TCP link
    link: str = ""                 # zenoh: "stall" | "reset" at the fault time
    device: str = "sim"            # sim | remote (stall, crash)


def _both(**kw) -> tuple[dict, dict]:
    return dict(kw, seed=11), dict(kw, seed=12)


def _matrix() -> list[Case]:
    out = []

    def add(name, **kw):
        c2s, s2c = _both(**kw)
        out.append(Case(name, c2s=c2s, s2c=s2c))

    add("baseline (no impairment)")
    add("loss 5% uniform", loss=0.05)
    add("loss 30% uniform", loss=0.30)
    add("loss 5% bursty", burst=_bursty(0.05))
    add("loss 30% bursty", burst=_bursty(0.30))
    add("delay 20 ms", delay_s=0.020)
    add("delay 100 ms", delay_s=0.100)
    add("jitter 50 ms (delay 50 +- 50 ms)", delay_s=0.050, jitter_s=0.050)
    add("duplication 1%", duplicate=0.01)
    add("reordering 25%", reorder=0.25)
    add("corruption 1%", corrupt=0.01)
    add("all at once (30% bursty, 20+-10 ms, 1% dup, 25% reorder, 1% corrupt)", burst=_bursty(0.30),
        delay_s=0.020, jitter_s=0.010, duplicate=0.01, reorder=0.25, corrupt=0.01)
    out += [
        Case("environment silent 400 ms", kind="silent"),
        Case("client killed mid-contact", kind="kill"),
        Case("client Bye mid-contact", kind="bye"),
        Case("server loop stalled 100 ms (remote device): recovers", kind="stall", device="remote"),
        Case("server loop killed (remote device, telemetry)", kind="crash", device="remote"),
        Case("zenoh baseline (through the TCP proxy)", transport="zenoh"),
        Case("zenoh TCP delay 20 ms", transport="zenoh", tcp_delay_s=0.020),
        Case("zenoh TCP delay 100 ms", transport="zenoh", tcp_delay_s=0.100),
        Case("zenoh link stalled 400 ms", transport="zenoh", kind="run", link="stall"),
        Case("zenoh link reset mid-contact", transport="zenoh", kind="run", link="reset"),
        Case("zenoh messages 30% bursty loss, 1% dup, 25% reorder", transport="zenoh",
             c2s=dict(burst=_bursty(0.30), duplicate=0.01, reorder=0.25, seed=21),
             s2c=dict(burst=_bursty(0.30), duplicate=0.01, reorder=0.25, seed=22)),
        Case("zenoh client killed mid-contact", transport="zenoh", kind="kill"),
    ]
    return out


CASES = _matrix()


# ------------------------------------------------------------------------------ the rig
def settings_for(url: str, *, device: str = "sim", device_port: int = 0, realtime: bool = True,
                 seconds: float = 10.0, device_watchdog_s: float = DEVICE_WATCHDOG_S, flush_rows: int = 512,
                 protocol_thread: bool = False):
    from ..server import config as cfgmod

    if device == "sim":
        dev = {"driver": "sim", "kind": "planar", "damping_n_s_per_m": DEVICE_DAMPING, "watchdog_s": device_watchdog_s,
               "workspace_min_m": WORKSPACE[0], "workspace_max_m": WORKSPACE[1],
               "hand": {"type": "constant", "wrench": [0.0, PUSH_N, 0.0]}}
    else:
        dev = {"driver": "remote", "kind": "planar", "listen": f"127.0.0.1:{device_port}", "connect_timeout_s": 20.0,
               "link_timeout_s": 0.1, "watchdog_s": DEVICE_WATCHDOG_S,
               "workspace_min_m": WORKSPACE[0], "workspace_max_m": WORKSPACE[1]}
    return cfgmod.load({
        "loop": {"rate_hz": RATE_HZ, "realtime": realtime, "protocol_thread": protocol_thread},
        "transport": {"url": url},
        "status": {"address": f"127.0.0.1:{_port()}"},
        "model": {"epsilon_m": 0.005},
        "device": dev,
        "telemetry": {"ring_s": seconds + 10.0, "flush_rows": flush_rows},
    })


def _device_main(port: int, out_path: str, seconds_max: float, stop, ready, hand: dict | None = None) -> None:
    """The remote device program (its own process): a simulated planar device, the same hand
    (or ``hand``), watchdog 50 ms; records per tick what the device rendered."""
    from ..server.devices.remote import DeviceProgram
    from ..server.devices.sim import SimDevice, parse_sim_config

    period_ns = 1_000_000
    sim = SimDevice(parse_sim_config({
        "kind": "planar", "damping_n_s_per_m": DEVICE_DAMPING, "watchdog_s": 0.0,
        "workspace_min_m": WORKSPACE[0], "workspace_max_m": WORKSPACE[1],
        "hand": hand or {"type": "constant", "wrench": [0.0, PUSH_N, 0.0]}}, period_s=period_ns * 1e-9))
    prog = DeviceProgram(sim, ("127.0.0.1", port), watchdog_s=DEVICE_WATCHDOG_S, period_s=period_ns * 1e-9)
    n = int(seconds_max * 1000) + 2000
    # t_s (CLOCK_MONOTONIC), armed, fault, epoch, fx, fy, tz (rendered), last accepted command t_s
    rec = np.zeros((n, 8))
    i = 0
    deadline = time.monotonic_ns()
    ready.set()
    try:
        while not stop.is_set() and i < n:
            prog.tick()
            now = time.monotonic_ns()
            w = sim.last_command
            rec[i] = (now * 1e-9, prog.armed, prog.fault, prog.key[1], w[0], w[1], w[5], prog._last_cmd_ns * 1e-9)
            i += 1
            deadline += period_ns
            if now > deadline + 5 * period_ns:
                deadline = now
            elif deadline > now:
                time.sleep((deadline - now) * 1e-9)
    finally:
        prog.close()
        np.save(out_path, rec[:i])


class DeviceProcess:
    """The remote device program in its own process (``_device_main``), started and stopped
    around a case; ``record()`` is what it rendered, per tick, once stopped."""

    def __init__(self, port: int, folder: str, seconds_max: float, hand: dict | None = None) -> None:
        ctx = mp.get_context("spawn")
        self.stop, ready = ctx.Event(), ctx.Event()
        self.out = str(Path(folder) / "device.npy")
        self.proc = ctx.Process(target=_device_main, args=(port, self.out, seconds_max, self.stop, ready),
                                kwargs={"hand": hand}, name="fault-device", daemon=True)
        self.proc.start()
        ready.wait(60)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def close(self) -> None:
        self.stop.set()
        self.proc.join(20)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(5)

    def record(self):
        return np.load(self.out) if os.path.exists(self.out) else None


class _Silencer:
    """Wraps a relay direction's decider: drops everything while ``on``."""

    LOST = Decision(True, None, 0, False, ())

    def __init__(self, decide) -> None:
        self.decide = decide
        self.on = False

    def __call__(self, nbytes: int) -> Decision:
        d = self.decide(nbytes)  # keep the seeded stream in step
        return self.LOST if self.on else d


@contextmanager
def _impaired_runner_transport(c2s: dict, s2c: dict):
    """While active, ClientRunner opens its transport wrapped in ImpairedTransport."""
    from ..clients import runner as runner_mod
    from ..testing.impair import ImpairedTransport

    real = runner_mod.open_transport

    def opened(url, role="client", **kw):
        return ImpairedTransport(real(url, role, **kw), send=Impairment(**c2s), recv=Impairment(**s2c))

    runner_mod.open_transport = opened
    try:
        yield
    finally:
        runner_mod.open_transport = real


def _engine(name: str):
    if name == "pymunk":
        from ..clients.pymunk_engine import PymunkEngine

        return PymunkEngine()
    from ..clients.stub_engine import StubEngine

    return StubEngine(seed=3)


class _ThreadClient:
    def __init__(self, engine_name: str, url: str, transport_options: dict | None = None, scene: str = "testbed") -> None:
        from ..clients.runner import ClientRunner

        self.engine = _engine(engine_name)
        self.runner = ClientRunner(self.engine, url, scene=scene, epsilon_m=0.005, max_contacts=16,
                                   connect_timeout_s=60.0, reconnect_delay_s=0.3,
                                   transport_options=transport_options)
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="fault-client", daemon=True)

    def _run(self) -> None:
        try:
            self.runner.run(self.stop)
        except BaseException as exc:  # noqa: BLE001 - reported in the row
            self.error = exc

    def start(self) -> "_ThreadClient":
        self.thread.start()
        return self

    def close(self) -> None:
        self.stop.set()
        self.thread.join(15)
        self.engine.close()


class _ProcessClient:
    """``hapticproxy client ENGINE`` in its own process (so it can be SIGKILLed)."""

    def __init__(self, engine_name: str, url: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hapticproxy.cli.main", "client", engine_name, "--scene", "testbed", "--connect", url,
             "--connect-timeout", "60", "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.error = None

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def _serve(sup, seconds: float, until=None) -> bool:
    """Serve status and drain telemetry for ``seconds`` or until ``until()`` is true."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        sup._serve_status(0.02)
        if sup.writer is not None:
            sup.writer.drain(sup.shared)
        if until is not None and until():
            return True
    return until is None


def _ring(sup) -> np.ndarray:
    head = int(sup.shared.head[0])
    n = min(head, sup.ring_rows)
    return sup.shared.ring[np.arange(head - n, head) % sup.ring_rows].copy()


def run_case(case: Case, *, engine: str = "pymunk", realtime: bool = True, seconds: float = 6.0,
             device_watchdog_s: float = DEVICE_WATCHDOG_S, workdir: str | None = None, keep_rows: bool = False,
             protocol_thread: bool = False) -> dict:
    """Run one case; returns its row (see the module docstring). ``protocol_thread``: the server's
    ``[loop] protocol_thread`` (the tick in a clock thread of its own)."""
    from ..server import telemetry
    from ..server.daemon import Supervisor

    tmp = tempfile.TemporaryDirectory(prefix="hp-faults-", dir=workdir)
    events: dict = {}
    relay = proxy = client = dev_proc = patch = None
    rec_path = Path(tmp.name) / "run.mcap"
    crash_info: dict = {}
    extra: dict = {}
    with ExitStack() as opened:  # closes what this run opened, the last first, also after an error
        if case.transport == "udp":
            url = f"udp://127.0.0.1:{_port()}"
        else:
            url = f"zenoh://127.0.0.1:{_port(socket.SOCK_STREAM)}/faults{os.getpid()}"
        dev_port = _port() if case.device == "remote" else 0
        s = settings_for(url, device=case.device, device_port=dev_port, realtime=realtime, seconds=seconds + 10,
                         device_watchdog_s=device_watchdog_s, flush_rows=64 if case.kind == "crash" else 512,
                         protocol_thread=protocol_thread)
        if case.device == "remote":
            dev_proc = DeviceProcess(dev_port, tmp.name, seconds + 60)
            opened.callback(dev_proc.close)
        sup = Supervisor(s, record=str(rec_path))
        opened.callback(sup.close)
        sup.start()
        rec_start = sup.writer._read  # the ring row the recording starts at
        loop_pid = int(sup.shared.status[sup._st("pid")])
        client_url = url
        topts = None
        if case.transport == "udp" and case.kind not in ("stall", "crash"):
            relay = ImpairingRelay(("127.0.0.1", int(url.rsplit(":", 1)[1])),
                                   c2s=Impairment(**case.c2s), s2c=Impairment(**case.s2c))
            opened.callback(relay.close)
            if case.kind == "silent":
                relay.c2s.decide = _Silencer(relay.c2s.decide)
            relay.start()
            client_url = relay.url
        elif case.transport == "zenoh":
            from ..testing.impair_tcp import ImpairingTcpProxy

            zport = int(url.split(":")[2].split("/")[0])
            proxy = ImpairingTcpProxy(("127.0.0.1", zport), delay_s=case.tcp_delay_s, seed=5).start()
            opened.callback(proxy.close)
            client_url = f"zenoh://127.0.0.1:{proxy.address[1]}/faults{os.getpid()}"
            topts = {"connect_timeout_s": 10.0}
        if case.kind == "kill":
            client = _ProcessClient(engine, client_url + ("?connect_timeout_s=10" if case.transport == "zenoh" else ""))
        elif case.c2s and case.transport == "zenoh":
            patch = _impaired_runner_transport(case.c2s, case.s2c)
            opened.enter_context(patch)
            client = _ThreadClient(engine, client_url, topts).start()
        else:
            client = _ThreadClient(engine, client_url, topts).start()
        opened.callback(client.close)
        # the session opens; the hand pushes the peg onto the wall
        if not _serve(sup, 90.0, lambda: sup.shared.get("updates") > 0):
            raise RuntimeError("the client never engaged the server")
        t_engaged = time.monotonic()
        fault_at = SETTLE_S if case.kind != "run" or case.link else seconds
        _serve(sup, max(0.0, t_engaged + fault_at - time.monotonic()))
        events["fault_s"] = time.monotonic()
        if case.kind == "silent":
            relay.c2s.decide.on = True
            _serve(sup, SILENT_S)
            relay.c2s.decide.on = False
            events["fault_end_s"] = time.monotonic()
        elif case.kind == "kill":
            client.kill()
        elif case.kind == "bye":
            client.stop.set()
            client.thread.join(10)
        elif case.kind == "stall":
            os.kill(loop_pid, signal.SIGSTOP)
            try:
                time.sleep(0.1)
            finally:
                os.kill(loop_pid, signal.SIGCONT)
            events["fault_end_s"] = time.monotonic()
            _serve(sup, 0.25)
            events["state_after_stall"] = sup.shared.snapshot()["loop_state"]  # in fault: recovers by itself
        elif case.kind == "crash":
            head_before = int(sup.shared.head[0])
            os.kill(loop_pid, signal.SIGKILL)
            sup.proc.join(10)
            # what the file holds right after the crash, before the supervisor drains the rest
            meta_now, rows_now = telemetry.read(rec_path)
            crash_info = {"rows": int(sup.shared.head[0]) - rec_start, "head_before": head_before,
                          "file_rows_at_crash": len(rows_now), "flushed_at_crash": sup.writer.rows_written,
                          "torn_at_crash": meta_now["torn_bytes"], "flush_rows": sup.writer.flush_rows}
        elif case.link == "stall":
            proxy.stall(SILENT_S)
        elif case.link == "reset":
            proxy.reset_links()
        if case.kind != "run" or case.link:
            _serve(sup, AFTER_S if case.kind != "stall" else AFTER_S + 0.5)
        events["end_s"] = time.monotonic()
        if relay is not None:
            extra["relay_c2s"] = relay.c2s.counters.as_dict()
            extra["relay_s2c"] = relay.s2c.counters.as_dict()
        if proxy is not None:
            extra["tcp_proxy"] = proxy.counters.as_dict()
        if patch is not None and client is not None and client.runner.transport is not None:
            tr = client.runner.transport
            extra["impaired_send"] = tr.counters_send.as_dict()
            extra["impaired_recv"] = tr.counters_recv.as_dict()
        snap = sup.shared.snapshot()
        rows = _ring(sup)
        t0_s = snap["t_start_ns"] * 1e-9
        if case.kind == "stall":
            # the device is re-enabled when the loop recovers (instead of a person's re-arm)
            from ..server.lifecycle import Reason

            rec = [t_ns for _, t_ns, _f, _t, r, _d in sup.shared.transitions_since(0) if r == Reason.RECOVERED]
            if rec:
                events["rearm_s"] = rec[0] * 1e-9
    dev_rec = dev_proc.record() if dev_proc is not None else None
    if case.kind == "crash":
        meta, file_rows = telemetry.read(rec_path)
        crash_info.update(file_rows=len(file_rows), torn_bytes=meta["torn_bytes"])
    tmp.cleanup()
    limits = limits_from(s, snap)
    ev_rel = {k: v - t0_s for k, v in events.items() if k.endswith("_s")}
    row = analyse(rows, limits, ev_rel, case)
    if dev_rec is not None:
        dev = analyse_device(dev_rec, limits, {k: v for k, v in events.items() if k.endswith("_s")}, case)
        row.update(dev)
        row["broken"] = {**row["broken"], **dev["device_broken"]}
        row["violations"] = row["server_violations"] + row["device_violations"]
    if crash_info:
        # at the crash every flushed block is readable (nothing torn); the supervisor then drains
        # the rest of the ring (shared memory outlives the loop process): nothing is lost
        row["telemetry_rows"] = crash_info["rows"]
        row["telemetry_in_file_at_crash"] = crash_info["file_rows_at_crash"]
        row["telemetry_flush_rows"] = crash_info["flush_rows"]
        row["telemetry_rows_lost"] = crash_info["rows"] - crash_info["file_rows"]
        row["telemetry_torn_bytes"] = crash_info["torn_at_crash"] + crash_info["torn_bytes"]
        if (crash_info["file_rows_at_crash"] != crash_info["flushed_at_crash"] or row["telemetry_torn_bytes"]
                or row["telemetry_rows_lost"]):
            row["broken"]["telemetry"] = 1
            row["violations"] += 1
    if "state_after_stall" in events:
        from ..server.shm import TEL

        row["state_after_stall"] = events["state_after_stall"]
        row["stall_trips"] = int(snap["stall_trips"])
        row["stall_recoveries"] = int(snap["stall_recoveries"])
        if "rearm_s" not in ev_rel:
            row["broken"]["no recovery after the stall"] = 1
            row["violations"] += 1
        else:
            after = rows[:, TEL["t_s"]] >= ev_rel["rearm_s"]
            f = np.abs(rows[after][:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_fz"]]])
            row["max_force_after_recovery_n"] = round(float(f.max()), 3) if len(f) else None
    row.update(case=case.name, faults=int(snap["faults_total"]), updates=int(snap["updates"]),
               missed_deadlines=int(snap["missed_deadlines"]), rt_scheduling=bool(snap["rt_scheduling"]))
    row.update(extra)
    if keep_rows:
        row["_rows"] = rows
        row["_events"] = ev_rel
        row["_device"] = dev_rec
    err = getattr(client, "error", None)
    if err is not None:
        row["client_error"] = f"{type(err).__name__}: {err}"
    return row


# ------------------------------------------------------------------------------ analysis
def limits_from(settings, snap: dict) -> dict:
    """What :func:`analyse` checks against: the loop's own caps and rates (status) and the
    ``[safety]`` times. The torque cap is the device's (0.5 N m for the planar sim device)."""
    from ..server.config import FIRST_COMMAND_MAX_N

    saf = settings["safety"]
    return dict(force_cap_n=snap["force_cap_n"], rate_limit_n_per_step=snap["rate_limit_n_per_step"],
                torque_cap_n_m=min(saf["max_torque_n_m"], 0.5),
                torque_rate_n_m_per_step=saf["torque_rate_n_m_per_s"] / settings.rate_hz,
                fade_s=saf["fade_s"], watchdog_s=saf["watchdog_s"], ramp_in_s=saf["ramp_in_s"],
                first_max_n=FIRST_COMMAND_MAX_N, period_s=1.0 / settings.rate_hz)


def analyse(rows: np.ndarray, lim: dict, ev: dict, case: Case | None = None) -> dict:
    """Promise checks over the server's telemetry rows (the TEL layout of server/shm.py).

    ``ev``: event times in the telemetry's time base (s since the loop started): ``fault_s``,
    ``fault_end_s``, ``rearm_s``, ``end_s``."""
    from ..server.shm import LS, TEL

    t = rows[:, TEL["t_s"]]
    state = rows[:, TEL["loop_state"]]
    gain = rows[:, TEL["gain"]]
    upd = rows[:, TEL["updates"]]
    f = rows[:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_fz"]]]
    tq = rows[:, [TEL["cmd_tx"], TEL["cmd_ty"], TEL["cmd_tz"]]]
    dt = lim["period_s"]
    cap_f, cap_t = lim["force_cap_n"], lim["torque_cap_n_m"]
    rate_f, rate_t = lim["rate_limit_n_per_step"], lim["torque_rate_n_m_per_step"]
    broken: dict = {}
    bad = np.zeros(len(rows), dtype=bool)

    def mark(name: str, mask: np.ndarray) -> None:
        mask = np.asarray(mask, dtype=bool)
        k = int(mask.sum())
        if k:
            broken[name] = broken.get(name, 0) + k
            bad[:] |= mask

    finite = np.isfinite(f).all(axis=1) & np.isfinite(tq).all(axis=1)
    mark("non-finite", ~finite)
    af = np.abs(np.nan_to_num(f, nan=np.inf))
    at = np.abs(np.nan_to_num(tq, nan=np.inf))
    mark("force over cap", (af > cap_f + TOL).any(axis=1) | (at > cap_t + TOL).any(axis=1))
    df = np.zeros_like(af)
    dq = np.zeros_like(at)
    df[1:] = np.abs(np.diff(f, axis=0))
    dq[1:] = np.abs(np.diff(tq, axis=0))
    # a cut (the fault policy's output "cut": a device fault, a stall trip) is zero at once, by
    # design: a step to exactly zero on a row in fault is that, whatever the force was before
    cut = (state == LS["fault"]) & ~np.any(f != 0.0, axis=1) & ~np.any(tq != 0.0, axis=1)
    mark("step over rate limit", ((df > rate_f + TOL).any(axis=1) | (dq > rate_t + TOL).any(axis=1)) & ~cut)
    mark("over the fade/ramp envelope", (af > gain[:, None] * cap_f + TOL).any(axis=1)
         | (at > gain[:, None] * cap_t + TOL).any(axis=1))
    # a fade (the gain going down: watchdog, session ended, fault, stop) never pushes harder
    gdown = np.zeros(len(rows), dtype=bool)
    gdown[1:] = gain[1:] < gain[:-1]
    grow = np.zeros(len(rows), dtype=bool)
    grow[1:] = (af[1:] > af[:-1] + TOL).any(axis=1) | (at[1:] > at[:-1] + TOL).any(axis=1)
    mark("force grew during a fade", gdown & grow)
    # a ramp (the gain going up) adds force at its own slope at most: cap * dt / ramp_in_s per step
    gup = np.zeros(len(rows), dtype=bool)
    gup[1:] = gain[1:] > gain[:-1]
    ramp = dt / lim["ramp_in_s"]
    fast = np.zeros(len(rows), dtype=bool)
    fast[1:] = ((af[1:] - af[:-1]) > cap_f * ramp + TOL).any(axis=1) | ((at[1:] - at[:-1]) > cap_t * ramp + TOL).any(axis=1)
    mark("force grew faster than the ramp", gup & fast)
    # ramp-ins from zero: the first command at most FIRST_COMMAND_MAX_N
    ramp_idx = np.nonzero((gain[1:] > 0) & (gain[:-1] <= 0))[0] + 1
    first_after = 0.0
    for i in ramp_idx:
        m = max(af[i].max(), at[i].max())
        first_after = max(first_after, m)
        if m > lim["first_max_n"] + TOL:
            broken["first command after ramp-in"] = broken.get("first command after ramp-in", 0) + 1
            bad[i] = True
    # watchdog: silent longer than watchdog_s (+1 step) and still engaged; counted, as the loop
    # counts it, from the end of the loop's own last stall (a gap of 10 periods or more between
    # rows: while the loop did not run, the environment's updates waited in its socket)
    new_upd = np.zeros(len(rows), dtype=bool)
    new_upd[1:] = upd[1:] > upd[:-1]
    last_upd_t = np.full(len(rows), np.nan)
    cur = np.nan
    for i in range(len(rows)):
        if new_upd[i] or (i == 0 and upd[0] > 0):
            cur = t[i]
        elif i > 0 and t[i] - t[i - 1] >= 10 * dt and np.isfinite(cur):
            cur = t[i]
        last_upd_t[i] = cur
    silent = t - last_upd_t
    mark("silent past the watchdog, still engaged",
         (state == LS["engaged"]) & (silent > lim["watchdog_s"] + 1.5 * dt) & np.isfinite(silent))
    # fades: from the step the loop starts fading, zero force within fade_s (+1 step)
    fading = (state == LS["fading"]) | (state == LS["stopping"])
    starts = np.nonzero(fading[1:] & ~fading[:-1])[0] + 1
    fade_ms = []
    detect_ms = []
    for i in starts:
        j = i
        while j < len(rows) and fading[j] and (af[j].max() > 0 or at[j].max() > 0):
            j += 1
        if j < len(rows) and af[j].max() == 0 and at[j].max() == 0:  # complete (then idle, or still fading)
            fade_ms.append((t[j] - t[i - 1]) * 1e3)
        if np.isfinite(last_upd_t[i - 1]) and state[i - 1] == LS["engaged"]:
            detect_ms.append((t[i] - last_upd_t[i - 1]) * 1e3)
        # the fade's time, plus the steps the rate limit needs if a skipped period (the loop woke
        # late) took the gain down faster than the output may follow
        allow = lim["fade_s"] + dt * (1.5 + math.ceil(max(af[i - 1].max() / rate_f, at[i - 1].max() / rate_t)))
        late = fading[i:] & (t[i:] - t[i - 1] > allow) & ((af[i:] > 0).any(axis=1) | (at[i:] > 0).any(axis=1))
        # only while this fade lasts
        end = i + int(np.argmax(~fading[i:])) if (~fading[i:]).any() else len(rows)
        late[end - i:] = False
        mark("fade not at zero within fade_s", np.concatenate([np.zeros(i, bool), late]))
    # stability over the last second before the fault (or the end)
    t_ref = ev.get("fault_s", t[-1]) if len(t) else 0.0
    full = (state == LS["engaged"]) & (gain >= 1.0)
    # settled: from FULL_GAIN_SETTLE_S after the last time the output was not at full gain (a ramp's
    # re-indexing and the deformation's recovery move the device on purpose)
    not_full_t = t[(t <= t_ref) & ~full]
    t_from = max(t_ref - 1.0, (not_full_t[-1] + FULL_GAIN_SETTLE_S) if len(not_full_t) else -np.inf)
    win = (t > t_from) & (t <= t_ref) & full
    from ..server.shm import TEL as _T

    dev_y = rows[:, _T["dev_y"]]
    settle_ptp_mm = float(np.ptp(dev_y[win]) * 1e3) if win.sum() > 10 else None
    settle_retrace_mm = float(retrace(dev_y[win]) * 1e3) if win.sum() > 10 else None
    force_ptp_n = float(np.ptp(f[win, 1])) if win.sum() > 10 else None
    at_cap = bool((af >= cap_f - 1e-6).any())
    engaged_rows = (state == LS["engaged"]) | (state == LS["fading"])
    unstable = bool(at_cap or (settle_retrace_mm is not None and settle_retrace_mm > 1.0)
                    or (force_ptp_n is not None and force_ptp_n > 1.0))
    mean_fy = float(np.mean(f[win, 1])) if win.sum() > 10 else None
    out = {
        "max_force_n": float(af.max()) if len(af) else 0.0,
        # the cut is zero at once by design; its size is reported on its own, not as a step
        "max_force_step_n": float(df[~cut].max()) if (~cut).any() else 0.0,
        "max_cut_n": float(df[cut].max()) if cut.any() else 0.0,
        "force_cap_n": cap_f,
        "rate_limit_n_per_step": rate_f,
        "fade_ms": round(max(fade_ms), 1) if fade_ms else None,
        "unstable": unstable,
        "force_ptp_n": None if force_ptp_n is None else round(force_ptp_n, 3),
        "violations": int(bad.sum()),
        "server_violations": int(bad.sum()),
        "broken": broken,
        "detect_ms": round(max(detect_ms), 1) if detect_ms else None,
        "first_after_ramp_n": round(first_after, 4) if len(ramp_idx) else None,
        "fades": int(len(starts)),
        "ramps": int(len(ramp_idx)),
        "settle_ptp_mm": None if settle_ptp_mm is None else round(settle_ptp_mm, 3),
        "settle_retrace_mm": None if settle_retrace_mm is None else round(settle_retrace_mm, 3),
        "contact_force_n": None if mean_fy is None else round(mean_fy, 3),
        "steps": int(len(rows)),
        "engaged_steps": int(engaged_rows.sum()),
    }
    return out


def retrace(y: np.ndarray) -> float:
    """The largest move back against the net motion of ``y`` (0 for a monotone signal; about
    twice the amplitude for an oscillation about a level)."""
    if len(y) < 2:
        return 0.0
    if y[-1] >= y[0]:
        return float(np.max(np.maximum.accumulate(y) - y))
    return float(np.max(y - np.minimum.accumulate(y)))


def analyse_device(rec: np.ndarray, lim: dict, ev: dict, case: Case) -> dict:
    """What the remote device rendered around a stall or a crash (times: CLOCK_MONOTONIC s)."""
    t, armed, fault, epoch = rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3]
    w = rec[:, 4:7]
    mag = np.abs(w).max(axis=1)
    broken: dict = {}
    nbad = 0
    t_f = ev["fault_s"]
    after = t >= t_f
    zero = after & (mag == 0) & (armed == 0)
    zero_ms = float((t[np.argmax(zero)] - t_f) * 1e3) if zero.any() else None
    # the device's own watchdog: no tick renders force once its last accepted command is older
    # than watchdog_s (the tick notices at its next period: a late tick of this non-real-time
    # program delays the cut, it does not break the rule)
    stale = (mag > 0) & (t - rec[:, 7] > DEVICE_WATCHDOG_S + 0.001)
    k = int(stale.sum())
    if k:
        broken["device output with no command for longer than its watchdog"] = k
        nbad += k
    # forces do not come back by themselves: from the cut on, nothing under the same command key
    # (epoch); only the server's next enable (a re-arm, or its recovery once on time) re-arms it
    t_rearm = ev.get("rearm_s", math.inf)
    t_zero = t[np.argmax(zero)] if zero.any() else math.inf
    cut_epoch = epoch[np.argmax(zero)] if zero.any() else -1
    back = (t > t_zero) & (epoch == cut_epoch) & (mag > 0)
    k = int(back.sum())
    if k:
        broken["device output after its watchdog cut, before the server re-enabled it"] = k
        nbad += k
    over = (np.abs(w[:, :2]) > lim["force_cap_n"] + TOL).any(axis=1) | (np.abs(w[:, 2]) > lim["torque_cap_n_m"] + TOL)
    if over.any():
        broken["device force over cap"] = int(over.sum())
        nbad += int(over.sum())
    first = None
    if math.isfinite(t_rearm):
        idx = np.nonzero((t >= t_rearm) & (mag > 0))[0]
        if len(idx):
            first = float(mag[idx[0]])
            if first > lim["first_max_n"] + TOL:
                broken["device first command after re-arm"] = 1
                nbad += 1
    trips = int(((fault[1:] != 0) & (fault[:-1] == 0)).sum())
    return {"zero_ms": None if zero_ms is None else round(zero_ms, 1), "device_violations": nbad,
            "device_broken": broken, "device_first_after_rearm_n": None if first is None else round(first, 4),
            "device_watchdog_trips": trips, "device_rendered_max_n": float(mag.max()) if len(mag) else 0.0}


# ------------------------------------------------------------------------------ CLI
def machine() -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{platform.machine()} {os.cpu_count()} cpus, {platform.system()} {platform.release()}, "
            f"load average {load:.2f} at start")


COLUMNS = ("case", "max_force_n", "max_force_step_n", "force_cap_n", "rate_limit_n_per_step", "fade_ms", "unstable",
           "peak_n", "steady_n", "recover_ms", "stall_trips", "max_force_norm_n", "max_torque_norm_n_m", "violations")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hapticproxy bench faults", description=doc_summary(__doc__))
    ap.add_argument("--json", action="store_true", help="one JSON object per line (default: a table, then JSON)")
    ap.add_argument("--engine", choices=("pymunk", "stub"), default="pymunk", help="testbed client engine")
    ap.add_argument("--cases", default="", help="comma-separated substrings of case names to run (default: all)")
    ap.add_argument("--seconds", type=float, default=6.0, help="seconds of each impairment case (default 6)")
    ap.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO for the loop")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    args = ap.parse_args(argv)
    from . import faults_lifecycle as lc
    from . import faults_safety as fs

    cases = CASES
    life = lc.cases()
    safety = fs.cases()
    if args.cases:
        wanted = [w.strip().lower() for w in args.cases.split(",") if w.strip()]
        cases = [c for c in CASES if any(w in c.name.lower() for w in wanted)]
        life = [c for c in life if any(w in c.name.lower() for w in wanted)]
        safety = [c for c in safety if any(w in c.name.lower() for w in wanted)]
    if args.list:
        for c in cases + life + safety:
            print(c.name)
        return 0
    if not cases and not life and not safety:
        print("hapticproxy bench faults: no case matches --cases", file=sys.stderr)
        return 2
    info = {"machine": machine(), "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "engine": args.engine, "rate_hz": RATE_HZ}
    if args.json:
        print_json({"run": info})
    rows = []
    this = sys.modules[__name__]
    for c in cases + life + safety:
        try:
            if isinstance(c, fs.SafetyCase):
                row = fs.run_case(c, this)
            elif isinstance(c, lc.LifecycleCase):
                row = lc.run_lifecycle_case(c, this, engine=args.engine, realtime=not args.no_realtime)
            else:
                row = run_case(c, engine=args.engine, realtime=not args.no_realtime, seconds=args.seconds)
        except Exception as exc:  # noqa: BLE001 - one failed case does not hide the others
            row = {"case": c.name, "error": f"{type(exc).__name__}: {exc}", "violations": None}
        rows.append(row)
        if args.json:
            print_json(row)
        else:
            print(f"{c.name}: " + ", ".join(f"{k} {row.get(k)}" for k in COLUMNS[1:]), file=sys.stderr, flush=True)
    total = sum(r["violations"] or 0 for r in rows if r.get("violations") is not None)
    errors = sum(1 for r in rows if "error" in r)
    unstable = sum(1 for r in rows if r.get("unstable"))
    summary = {"cases": len(rows), "violations": total, "unstable": unstable, "errors": errors}
    if args.json:
        print_json({"summary": summary})
    else:
        print(format_table(rows))
        print_json({"run": info, "summary": summary})
    return 0 if total == 0 and errors == 0 else 1


def format_table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "| " + " | ".join("---" for _ in COLUMNS) + " |"]
    for r in rows:
        cells = []
        for k in COLUMNS:
            v = r.get(k)
            if isinstance(v, float):
                v = f"{v:.3f}" if k != "fade_ms" else f"{v:.0f}"
            cells.append("-" if v is None else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
