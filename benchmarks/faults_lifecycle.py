"""The lifecycle cases of ``hapticproxy bench faults``: start-up, stalls, re-engagement.

Each case runs the real server (supervisor + loop process, 1 kHz, default ``[safety]``) with the
pymunk testbed client on UDP loopback and the simulated planar device, and returns one row like
the other cases (``bench_faults.analyse``: caps, rate limit, fade/ramp envelopes, watchdog) plus
its own figures:

- **cold start**: the loop process starts with an empty numba cache (``NUMBA_CACHE_DIR`` a new
  directory): ``compile_s`` until the loop was ready, ``late_compiles`` (kernels compiled once
  the loop ran: must be 0), ``stall_trips``, ``faults``;
- **stall before engagement**: the loop process stopped (SIGSTOP) for 100 ms before any client
  came: ``stall_trips`` (the device's watchdog did cut it), never in ``fault``;
- **stall while engaged** (60 / 120 / 250 ms): the device's watchdog cuts the output, the loop
  recovers by itself once on time for ``stall_recover_s``: ``recover_ms`` from the end of the
  stall to the force ramping in again, ``peak_n`` within 2 s of that and ``steady_n`` (the force
  at rest afterwards); a kick (``peak_n`` above ``steady_n`` + 1 N) is a violation;
- **repeated stalls**: four 80 ms stalls 1.2 s apart with ``stall_trips_max`` 3: the fourth
  latches (``fault`` stays ``stalls_repeated``, zero output until the end);
- **re-engagement** with the hand pushing 0.5 N as a pure force source and with a gripping
  (impedance) hand: the first engagement with the hand already pushing, a re-arm after a device
  fault (the remote device's link cut for 150 ms by stopping the device program), a new client
  50 ms after a Bye (the fade still running), a client restarted on the same socket (a new Hello
  from the same address): ``peak_n`` within 2 s of the engagement against ``steady_n``;
- **input no engine should send** (``MISREPORTS``): for 2 s, every second ContactUpdate carries
  absurd values (a constraint velocity of 1e9 m/s, a position or tool pose at 1e9 m, a 5 m
  penetration), contacts the tool cannot use (a z normal on the planar tool, tool link 3), or
  what real engines do (normals flipped, feature ids renumbered): the first kind must be refused
  and counted (``refused``), none may make the force step above the rate limit or pull the hand
  towards the surface (``max_pull_n``).
"""
from __future__ import annotations

import os
import signal
import tempfile
import threading
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field

import numpy as np

PUSH_N = 0.5
KICK_MARGIN_N = 1.0
AFTER_ENGAGE_S = 2.0     # the window of the no-kick promise
STEADY_S = 0.5           # the force at rest: the mean over the last half second
HAND = {
    # both from the server's start: the hand is already pushing when the first client engages
    "force": {"type": "constant", "start": "server", "wrench": [0.0, PUSH_N, 0.0]},
    # a soft arm gripping the handle and pulling it 5 cm down: about the same push, damped
    "grip": {"type": "impedance", "start": "server", "stiffness_n_per_m": 10.0, "damping_n_s_per_m": 5.0,
             "target": {"type": "constant", "pose": [0.0, 0.05, 0.0]}},
}


@dataclass
class LifecycleCase:
    name: str
    kind: str                      # cold | stall-idle | stall | stalls | first | rearm | bye50 | restart | input
    stall_ms: float = 0.0
    hand: str = "force"
    safety: dict = field(default_factory=dict)
    misreport: str = ""            # input: what every second ContactUpdate gets wrong (MISREPORTS)


#: What an engine may send that no engine should, applied to every second update for 2 s once the
#: peg rests on the wall: ``(counter in status that must count it, what is done to the contacts)``;
#: the first six must be refused before the model, the last two are real engines' habits the model
#: must take without a force step above the rate limit or a pull towards the surface.
MISREPORTS = {
    "v_constr 1e9 m/s": ("refused_out_of_bounds", lambda b, n, pose: b.v_constr_m_per_s[:n].fill(1e9)),
    "contact position 1e9 m": ("refused_out_of_bounds", lambda b, n, pose: b.position_m[:n, 0].fill(1e9)),
    "tool pose 1e9 m": ("refused_out_of_bounds", lambda b, n, pose: pose.__setitem__(0, 1e9)),
    "separation -5 m": ("refused_out_of_bounds", lambda b, n, pose: b.separation_m[:n].fill(-5.0)),
    "a z normal on a planar tool": ("refused_unusable", lambda b, n, pose: _tilt_normals(b, n)),
    "tool link 3 on a rigid tool": ("refused_unusable", lambda b, n, pose: b.keys[:n, 0].fill(3)),
    "normals flipped": ("", lambda b, n, pose: b.normal[:n].__imul__(-1.0)),
    "feature ids renumbered": ("", lambda b, n, pose: b.keys[:n, 2].__iadd__(1000)),
}


def _tilt_normals(b, n):
    b.normal[:n, 2] = 0.6
    b.normal[:n, :] /= np.linalg.norm(b.normal[:n], axis=1)[:, None]


class _Misreporting:
    """Wraps an engine: every second ContactUpdate is altered by ``alter(buf, n, pose)`` while
    ``on``; otherwise the engine is unchanged."""

    def __init__(self, engine, alter) -> None:
        self._e = engine
        self._alter = alter
        self.on = False
        self._k = 0
        self._pose_bad = False

    def contacts(self, buf, max_contacts):
        n = self._e.contacts(buf, max_contacts)
        self._k += 1
        self._pose_bad = False
        if self.on and self._k % 2 == 0 and n:
            probe = np.zeros(7)
            self._alter(buf, n, probe)
            self._pose_bad = probe[0] != 0.0
        return n

    def tool_pose(self, out):
        self._e.tool_pose(out)
        if self._pose_bad:
            out[0] = 1e9
        return out

    def __getattr__(self, name):
        return getattr(self._e, name)


def cases() -> list[LifecycleCase]:
    out = [LifecycleCase("cold start (empty numba cache)", "cold"),
           LifecycleCase("stall 100 ms before engagement", "stall-idle", 100.0)]
    out += [LifecycleCase(f"stall {ms:.0f} ms while engaged: recovers", "stall", ms) for ms in (60.0, 120.0, 250.0)]
    out.append(LifecycleCase("4 stalls of 80 ms within 5 s: the 4th latches", "stalls", 80.0,
                             safety={"stall_trips_max": 3, "stall_window_s": 60.0}))
    out += [LifecycleCase(f"every 2nd update: {what}", "input", misreport=what) for what in MISREPORTS]
    for hand in ("force", "grip"):
        what = "pushing hand" if hand == "force" else "gripping hand"
        out += [LifecycleCase(f"first engagement, {what} already pushing", "first", hand=hand),
                LifecycleCase(f"re-arm after a device fault, {what}", "rearm", hand=hand),
                LifecycleCase(f"new client 50 ms after a Bye, {what}", "bye50", hand=hand),
                LifecycleCase(f"client restart on the same socket, {what}", "restart", hand=hand)]
    return out


@contextmanager
def _env(name: str, value: str | None):
    old = os.environ.get(name)
    if value is not None:
        os.environ[name] = value
    try:
        yield
    finally:
        if value is None:
            pass
        elif old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


class _SharedSocket:
    """A client transport that outlives its runner: the next runner opens the same socket (a
    restarted engine process that binds its old port), and ``muted`` loses what it sends (a
    killed process says no Bye)."""

    def __init__(self, real) -> None:
        self.real = real
        self.muted = False

    def send(self, data) -> None:
        if not self.muted:
            self.real.send(data)

    def close(self) -> None:
        pass

    def __getattr__(self, name):
        return getattr(self.real, name)


@contextmanager
def _same_socket_runners():
    from ..clients import runner as runner_mod

    real_open = runner_mod.open_transport
    holder: dict = {}

    def opened(url, role="client", **kw):
        if "t" not in holder:
            holder["t"] = _SharedSocket(real_open(url, role, **kw))
        holder["t"].muted = False
        return holder["t"]

    runner_mod.open_transport = opened
    try:
        yield holder
    finally:
        runner_mod.open_transport = real_open
        if "t" in holder:
            holder["t"].real.close()


def _settings(bf, url: str, case: LifecycleCase, *, device: str = "sim", device_port: int = 0, seconds: float = 20.0,
              protocol_thread: bool = False):
    from ..server import config as cfgmod

    s = bf.settings_for(url, device=device, device_port=device_port, seconds=seconds, protocol_thread=protocol_thread)
    data = s.as_dict()
    data.pop("preset", None)
    if device == "sim":
        data["device"]["hand"] = HAND[case.hand]
    data["safety"].update(case.safety)
    return cfgmod.load(data)


def _transitions(sup) -> list[tuple]:
    from ..server.lifecycle import LOOP_STATES, Reason

    t0 = sup.shared.status[sup._st("t_start_ns")]
    return [((t_ns - t0) * 1e-9, LOOP_STATES[frm], LOOP_STATES[to], Reason(r).name.lower(), detail)
            for _, t_ns, frm, to, r, detail in sup.shared.transitions_since(0)]


def _kick(rows: np.ndarray, t_engage: float, row: dict) -> None:
    """Peak force within AFTER_ENGAGE_S of ``t_engage`` against the steady force at the end."""
    from ..server.shm import TEL

    t = rows[:, TEL["t_s"]]
    f = np.linalg.norm(rows[:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_fz"]]], axis=1)
    win = (t >= t_engage) & (t <= t_engage + AFTER_ENGAGE_S)
    end = t >= t[-1] - STEADY_S
    if not win.any():
        row["broken"]["no engagement"] = 1
        row["violations"] += 1
        return
    peak = float(f[win].max())
    steady = float(f[end].mean())
    row.update(peak_n=round(peak, 3), steady_n=round(steady, 3))
    if peak > steady + KICK_MARGIN_N:
        row["broken"]["kick at engagement"] = int((f[win] > steady + KICK_MARGIN_N).sum())
        row["violations"] += row["broken"]["kick at engagement"]


def run_lifecycle_case(case: LifecycleCase, bf, *, engine: str = "pymunk", realtime: bool = True,
                       protocol_thread: bool = False) -> dict:
    """Run one lifecycle case on the real server (``bf``: the bench_faults module; ``protocol_thread``:
    the server's ``[loop] protocol_thread``)."""
    from ..server.daemon import Supervisor
    from ..server.lifecycle import Fault

    url = f"udp://127.0.0.1:{bf._port()}"
    tmp = tempfile.TemporaryDirectory(prefix="hp-lifecycle-")
    remote = case.kind == "rearm"
    dev_port = bf._port() if remote else 0
    s = _settings(bf, url, case, device="remote" if remote else "sim", device_port=dev_port,
                  protocol_thread=protocol_thread)
    if not realtime:
        data = s.as_dict()
        data["loop"]["realtime"] = False
        from ..server import config as cfgmod
        s = cfgmod.load({k: v for k, v in data.items() if k != "preset"})
    clients: list = []
    dev_proc = None
    events: dict = {}
    extra: dict = {}
    same = None
    with ExitStack() as opened:  # closes what this run opened, the last first, also after an error
        opened.callback(tmp.cleanup)
        if remote:
            dev_proc = bf.DeviceProcess(dev_port, tmp.name, 120.0, hand=HAND[case.hand])
            opened.callback(dev_proc.close)
        t_start = time.monotonic()
        with _env("NUMBA_CACHE_DIR", os.path.join(tmp.name, "numba") if case.kind == "cold" else None):
            sup = Supervisor(s)
            opened.callback(sup.close)
            sup.start()
        extra["compile_s"] = round(time.monotonic() - t_start, 1) if case.kind == "cold" else None
        loop_pid = int(sup.shared.status[sup._st("pid")])
        if case.kind == "restart":
            same = opened.enter_context(_same_socket_runners())
        opened.callback(_close_each, clients)  # the runners, in the order they started

        # the re-engagement cases engage with the peg already resting in contact (the hole
        # scene: in the bottom hole), so what they measure is the engagement, not an approach
        scene = "hole" if case.kind in ("first", "rearm", "bye50", "restart", "input") else "testbed"

        def client():
            c = bf._ThreadClient(engine, url, scene=scene)
            if case.kind == "input":
                c.engine = _Misreporting(c.engine, MISREPORTS[case.misreport][1])
                c.runner.engine = c.engine
            c.start()
            clients.append(c)
            return c

        def engaged():
            return sup.shared.get("loop_state") == 1.0 and sup.shared.get("gain") > 0.0

        if case.kind == "stall-idle":
            bf._serve(sup, 0.3)
            _stall(loop_pid, case.stall_ms)
            bf._serve(sup, 0.5)
        if case.kind == "first":
            bf._serve(sup, 0.5)  # the hand pushes the free handle before any client
        c = client()
        if not bf._serve(sup, 90.0, lambda: sup.shared.get("updates") > 0):
            raise RuntimeError("the client never engaged the server")
        bf._serve(sup, bf.SETTLE_S)
        events["fault_s"] = time.monotonic()
        if case.kind == "stall":
            _stall(loop_pid, case.stall_ms)
            bf._serve(sup, 3.5)
        elif case.kind == "stalls":
            for _ in range(4):
                _stall(loop_pid, case.stall_ms)
                bf._serve(sup, 1.2)
            bf._serve(sup, 1.5)
        elif case.kind == "input":
            snap0 = sup.shared.snapshot()
            c.engine.on = True
            bf._serve(sup, 2.0)
            c.engine.on = False
            bf._serve(sup, 1.0)
            counter = MISREPORTS[case.misreport][0]
            if counter:
                extra["refused"] = int(sup.shared.get(counter) - snap0[counter])
        elif case.kind == "rearm":
            os.kill(dev_proc.pid, signal.SIGSTOP)  # the device program stops: its link is lost
            try:
                time.sleep(0.15)
            finally:
                os.kill(dev_proc.pid, signal.SIGCONT)
            bf._serve(sup, 0.6)                    # the hand pushes the dead handle on
            events["state_before_rearm"] = sup.shared.snapshot()["loop_state"]
            sup.shared.request("rearm")
            bf._serve(sup, 3.5)
        elif case.kind == "bye50":
            c.stop.set()
            c.thread.join(10)                      # the runner says Bye
            bf._serve(sup, 0.05)
            client()
            bf._serve(sup, 4.0)
        elif case.kind == "restart":
            same["t"].muted = True                 # the process dies without a word ...
            c.stop.set()
            c.thread.join(10)
            client()                               # ... and comes back on the same socket
            bf._serve(sup, 4.0)
        else:
            bf._serve(sup, 3.0)
        snap = sup.shared.snapshot()
        rows = bf._ring(sup)
        trans = _transitions(sup)
        t0_s = snap["t_start_ns"] * 1e-9
    limits = bf.limits_from(s, snap)
    ev_rel = {k: v - t0_s for k, v in events.items() if k.endswith("_s")}
    row = bf.analyse(rows, limits, ev_rel)
    row.update(case=case.name, faults=int(snap["faults_total"]), stall_trips=int(snap["stall_trips"]),
               stall_recoveries=int(snap["stall_recoveries"]), late_compiles=int(snap["late_compiles"]),
               updates=int(snap["updates"]), missed_deadlines=int(snap["missed_deadlines"]),
               fault=Fault(int(snap["fault"])).name.lower() if "fault" in snap else None,
               transitions=[f"{t:.3f} {a}->{b} ({r} {d:g})" for t, a, b, r, d in trans])
    row.update({k: v for k, v in extra.items() if v is not None})
    _judge(case, row, rows, trans, ev_rel)
    return row


def _close_each(items: list) -> None:
    for c in items:
        c.close()


def _stall(pid: int, ms: float) -> None:
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(ms * 1e-3)
    finally:
        os.kill(pid, signal.SIGCONT)


def _fail(row: dict, what: str, n: int = 1) -> None:
    row["broken"][what] = row["broken"].get(what, 0) + n
    row["violations"] += n


def _judge(case: LifecycleCase, row: dict, rows: np.ndarray, trans: list, ev: dict) -> None:
    """The case's own promises, counted as violations like the per-step ones."""
    from ..server.shm import TEL

    to_fault = [t for t in trans if t[2] == "fault"]
    engages = [t for t in trans if t[2] == "engaged"]
    if case.kind == "cold":
        if row["late_compiles"]:
            _fail(row, "kernels compiled after the loop was armed", row["late_compiles"])
        if to_fault or row["stall_trips"]:
            _fail(row, "a fault or stall trip at start-up")
    elif case.kind == "stall-idle":
        if to_fault:
            _fail(row, "a stall before engagement faulted")
        if row["stall_trips"] != 1:
            row["note"] = f"{row['stall_trips']} stall trips (the device's watchdog may not have seen this stall)"
    elif case.kind == "stall":
        # the injected stall's trip and recovery (a loaded machine may add stalls of its own)
        t_evt = ev.get("fault_s", 0.0) - 0.01
        rec = [t for t in trans if t[3] == "recovered" and t[0] >= t_evt]
        trip = [t for t in trans if t[3] == "stall" and t[0] >= t_evt]
        if not trip:
            row["note"] = "no stall trip (the device's watchdog did not trip)"
        elif not rec:
            _fail(row, "no recovery after the stall")
        else:
            row["recover_ms"] = round((rec[0][0] - trip[0][0]) * 1e3, 1)
            _kick(rows, rec[0][0], row)
    elif case.kind == "input":
        counter = MISREPORTS[case.misreport][0]
        if counter and not row.get("refused"):
            _fail(row, f"nothing refused as {counter}")
        if to_fault:
            _fail(row, "a fault")
        from ..server.shm import TEL as _T

        t = rows[:, _T["t_s"]]
        win = t >= ev.get("fault_s", 0.0)
        fy = rows[win][:, _T["cmd_fy"]]
        # the wall pushes the hand back (-y); a flipped normal must never pull it in (+y)
        row["max_pull_n"] = round(float(max(0.0, fy.max())), 4) if len(fy) else None
        if len(fy) and fy.max() > 1e-9:
            _fail(row, "a pull towards the surface", int((fy > 1e-9).sum()))
    elif case.kind == "stalls":
        latched = [t for t in trans if t[3] == "stalls_repeated"]
        if not latched:
            _fail(row, "repeated stalls did not latch")
        else:
            t = rows[:, TEL["t_s"]]
            after = t > latched[0][0] + 0.25      # the fade of whatever was left, then nothing
            f = np.abs(rows[after][:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_fz"]]])
            row["max_force_after_latch_n"] = round(float(f.max()), 4) if len(f) else None
            if len(f) and f.max() > 0:
                _fail(row, "force after the latch", int((f > 0).any(axis=1).sum()))
    else:
        # the engagement the case is about: the first one, or the last one after the event
        after = [t for t in engages if t[0] >= ev.get("fault_s", 0.0)]
        which = engages[:1] if case.kind == "first" else after[-1:]
        if not which:
            _fail(row, "no engagement")
        else:
            row["engaged_by"] = which[0][3]
            _kick(rows, which[0][0], row)


def run_all(bf, names: list[str] | None = None, **kw) -> list[dict]:
    out = []
    for c in cases():
        if names and not any(n in c.name.lower() for n in names):
            continue
        try:
            out.append(run_lifecycle_case(c, bf, **kw))
        except Exception as exc:  # noqa: BLE001 - one failed case does not hide the others
            out.append({"case": c.name, "error": f"{type(exc).__name__}: {exc}", "violations": None})
    return out


__all__ = ["LifecycleCase", "cases", "run_lifecycle_case", "run_all", "threading"]
