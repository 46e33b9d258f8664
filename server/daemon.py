"""``hapticproxy serve``: the supervisor process and the haptic-loop process it starts.

The haptic loop runs alone in its own process (a CPU-bound Python thread in the same process
makes the loop wake milliseconds late: the GIL). The supervisor owns everything slow: the config,
logging, the status server (``hapticproxy status``), the telemetry file, signals. The two share
one block of memory (``server/shm.py``); the supervisor never blocks the loop.

In the loop process: SIGINT is ignored (Ctrl-C reaches the supervisor, which asks for a clean
stop), SIGTERM asks for the same clean stop; after warm-up the garbage collector is frozen and
disabled, the timer slack set to 1 ns, SCHED_FIFO requested (the status says whether it was
granted), optionally pinned to a CPU, and the spin phase of the hybrid wait calibrated.

Clean stop (SIGINT/SIGTERM/``status --stop``/``--duration``): forces ramp to zero over
``safety.fade_s``, ``Bye`` goes to every client, telemetry is flushed, exit code 0. A stop
during start-up (while the loop process imports, builds, compiles or warms up) stops the loop
process before it runs (SIGTERM unwinds it through the ``finally`` that closes its device), also
exit code 0. A start-up failure is one line naming what failed: a taken transport or status
address exits 1 (it may be free later), one this machine does not have exits 2 (the config must
change). In ``ps`` the supervisor is ``hapticproxy serve ARGS`` and the loop ``hapticproxy-loop``.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import errno
import gc
import hmac
import json
import logging
import multiprocessing as mp
import os
import re
import select
import signal
import socket
import sys
import time
from typing import TYPE_CHECKING

from ..protocol.jsonout import dumps, jsonable  # noqa: F401 - re-exported (the status replies' rule)

from . import config as cfgmod
from .lifecycle import LOOP_STATES, Reason, describe
from .shm import SharedState

if TYPE_CHECKING:
    from .live import LiveView
    from .recording import McapRecorder

log = logging.getLogger("hapticproxy.serve")



# ------------------------------------------------------------------------------ loop process
class _StopDuringStartup(BaseException):
    """SIGTERM reached the loop process before its loop ran (while it imports, builds, compiles or
    warms up): unwind through the ``finally`` that closes the device, exit 0. A BaseException, so
    no ``except Exception`` on the way swallows it."""


def _raise_stop(signum, frame):  # noqa: ARG001
    raise _StopDuringStartup


def set_process_title(title: str) -> None:
    """Name this process in ``ps``/``top`` (setproctitle; nothing happens without it)."""
    try:
        from setproctitle import setproctitle
    except ImportError:  # pragma: no cover - a declared dependency
        return
    setproctitle(title)


LOOP_TITLE = "hapticproxy-loop"


def loop_process_main(data, shm_name: str, ring_rows: int, hmac_key: bytes | None, naive: bool = False,
                      report=None) -> None:
    """Entry point of the loop process (spawned). ``naive``: the comparison baseline of
    ``bench loop``: the same work paced by ``time.sleep`` alone, with none of the tuning.
    ``report``: the sending end of a pipe; a start-up failure sends ``(message, exit code)`` on it,
    so the supervisor prints one line that names what failed (a taken transport address...).
    ``data``: the supervisor's ``Settings`` (or their tables as a dict)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the supervisor's to handle
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    # a stop before the try below has nothing to clean up: exit at once (raising then was a
    # traceback from wherever the signal landed, e.g. inside _die_with_parent)
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    set_process_title(LOOP_TITLE)
    from ..protocol import logs

    logs.configure(logging.INFO)
    llog = logging.getLogger("hapticproxy.loop")
    parent = os.getppid()
    _die_with_parent()
    shared = SharedState.attach(shm_name, ring_rows)
    st = shared.status
    from .shm import ST

    st[ST["pid"]] = os.getpid()
    code = 0
    loop = None
    transport = None
    latency_fd = None
    running = False
    signal.signal(signal.SIGTERM, _raise_stop)  # from here a stop unwinds through the finally below
    try:
        from .clock import MonotonicClock, SleepClock, hold_cpu_latency, pin_to_cpu, set_timer_slack_ns, try_realtime
        from .loop import HapticLoop

        settings = data if isinstance(data, cfgmod.Settings) else cfgmod.Settings(data, "<supervisor>")
        lcfg = settings["loop"]
        clock = SleepClock() if naive else MonotonicClock()
        transport = open_server_transport(settings["transport"]["url"])
        bound = getattr(transport, "local_address", None)
        st[ST["transport_port"]] = bound[1] if isinstance(bound, tuple) and len(bound) >= 2 else 0
        loop = HapticLoop.build(settings, clock=clock, transport=transport, shared=shared, hmac_key=hmac_key)
        loop.parent_pid = parent  # a loop whose supervisor died stops (forces fade, Bye, exit)
        llog.debug("pid %d: transport %s open, %s device %r built", os.getpid(), transport.url,
                   settings["device"]["kind"], settings["device"]["driver"])
        _send_device_info(report, loop.device, settings, loop.settings)
        from .warm import refresh_stale_caches

        refresh_stale_caches()  # kernels compiled from older sources would run the old code
        todo = loop.cold_kernels()
        t_warm = time.monotonic()
        if todo:
            llog.info("compiling %d kernel%s before the loop starts (not cached on this machine yet: a few "
                      "minutes on 2 cores; `hapticproxy warmup` does it ahead) ...", len(todo), "s" * (len(todo) != 1))
        loop.warm_up()
        if todo:
            llog.info("kernels compiled in %.1f s; numba cached them for the next start", time.monotonic() - t_warm)
        llog.debug("kernels warm")

        def on_term(signum, frame):  # noqa: ARG001 - checked in housekeeping, never in a kernel
            loop._stop_flag = True

        if naive:
            signal.signal(signal.SIGTERM, on_term)
            running = True
            loop.start()
            loop.run()
            return
        st[ST["timer_slack"]] = 1.0 if set_timer_slack_ns(1) else 0.0
        if lcfg["cpu"] >= 0:
            pin_to_cpu(lcfg["cpu"])
        if lcfg["spin_us"] == "auto":
            clock.calibrate()
        else:
            clock.spin_ns = int(lcfg["spin_us"] * 1000)
        st[ST["spin_ns"]] = clock.spin_ns
        rt = False
        if lcfg["realtime"]:
            rt, why = try_realtime()
            if not rt:
                llog.warning("real-time scheduling not granted: %s", why)
        st[ST["rt_scheduling"]] = 1.0 if rt else 0.0
        if lcfg["cpu_latency_us"] != "off":
            latency_fd, why = hold_cpu_latency(lcfg["cpu_latency_us"])
            if latency_fd is None:
                llog.warning("idle CPUs' wake-up latency not held (deadlines may wake later): %s", why)
            else:
                st[ST["cpu_latency_us"]] = lcfg["cpu_latency_us"]
        gc.collect()
        gc.freeze()
        gc.disable()
        signal.signal(signal.SIGTERM, on_term)  # from now on a stop ramps the forces down
        running = True
        loop.start()
        loop.run()
    except _StopDuringStartup:
        llog.info("stopped during start-up")
    except StartupError as exc:
        _report(report, str(exc), exc.code)
        code = exc.code
    except ValueError as exc:
        if running or not (str(exc).startswith("device") or isinstance(exc, cfgmod.ConfigError)):
            raise
        # a device that cannot be used as configured, or a gain it cannot take: one line, the fix in it
        _report(report, str(exc), 2)
        code = 2
    except Exception as exc:  # noqa: BLE001 - reported to the supervisor, then exit non-zero
        why = f"{type(exc).__name__}: {exc}"
        if running:
            llog.error("%s", why)
        else:
            _report(report, f"the loop process failed to start: {why}", 1)
        code = 1
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the clean-up below is not interrupted
        if loop is not None:
            try:
                loop.close()
            except Exception:  # noqa: BLE001
                pass
        if transport is not None:
            transport.close()
        if latency_fd is not None:
            os.close(latency_fd)
        st[ST["exit_code"]] = code
        st[ST["loop_state"]] = LOOP_STATES.index("stopped")
        # The supervisor owns the block and unlinks it when it closes. One that died (SIGKILL)
        # left this process its last user: unlinking it here also unregisters it from the
        # resource tracker both processes share (spawn), which would otherwise find it at exit,
        # unlink it and warn of a leaked shared_memory object.
        shared.close(unlink=os.getppid() != parent)
    sys.exit(code)


#: the first element of the message that carries the device's info (not a failure)
DEVICE_INFO = "\0device-info"


def _send_device_info(conn, device, before=None, after=None) -> None:
    """Tell the supervisor what the device is (``status`` shows it), with what the gains became
    on it (``derived``: the defaults lowered to what the device takes, the set gains let through
    beyond it by the research override; ``devices/safe.py``)."""
    if conn is None:
        return
    try:
        info = device.info.as_dict()
        if before is not None and after is not None:
            info["derived"] = {"lowered": [list(x) for x in after.lowered[len(before.lowered):]],
                               "outside": [list(x) for x in
                                           after.outside_stable_region[len(before.outside_stable_region):]]}
        conn.send((DEVICE_INFO, info))
    except Exception:  # noqa: BLE001 - a driver whose info cannot be read: status shows none
        pass


def _report(conn, message: str, code: int) -> None:
    if conn is None:
        print(f"hapticproxy loop: {message}", file=sys.stderr)
        return
    try:
        conn.send((message, code))
    except (OSError, ValueError):
        print(f"hapticproxy loop: {message}", file=sys.stderr)


class StartupError(RuntimeError):
    """The server cannot start; ``code`` is the exit status (2: the config or the command line
    must change, 1: something at run time, e.g. an address another process holds)."""

    def __init__(self, message: str, code: int = 1) -> None:
        super().__init__(message)
        self.code = code


_OS_ERROR = re.compile(r"os error (\d+)")


def address_error(what: str, address: str, exc: BaseException) -> StartupError:
    """One line naming the setting and the address that cannot be bound, and why. A taken address
    is a run-time condition (exit 1: it may be free later); an address this machine does not
    have, an unknown host or a forbidden port is the configuration's (exit 2)."""
    err = getattr(exc, "errno", None)
    if not isinstance(exc, OSError) or err is None:
        m = _OS_ERROR.search(str(exc))  # Zenoh reports the OS error inside its text
        err = int(m.group(1)) if m else None
    if isinstance(exc, socket.gaierror):
        return StartupError(f"{what} {address}: unknown host ({exc.strerror})", 2)
    if err == errno.EADDRINUSE:
        return StartupError(f"{what} {address}: address already in use (another server running?)", 1)
    if err == errno.EADDRNOTAVAIL:
        return StartupError(f"{what} {address}: not an address of this machine (cannot assign it)", 2)
    if err == errno.EACCES:
        return StartupError(f"{what} {address}: permission denied (a port below 1024 needs privileges)", 2)
    why = os.strerror(err) if err else (getattr(exc, "strerror", None) or str(exc))
    return StartupError(f"{what} {address}: cannot bind ({why})", 1)


def open_server_transport(url: str):
    """The server's transport endpoint at ``url``; :class:`StartupError` naming
    ``transport.url`` and the address when it cannot be opened."""
    from ..protocol.transport import TransportError, open_transport

    try:
        return open_transport(url, "server")
    except (OSError, TransportError) as exc:
        raise address_error("transport.url", url, exc) from None


def _die_with_parent() -> None:
    """Linux: SIGTERM this process when the supervisor dies (e.g. SIGKILL), so a loop is never
    left rendering forces with nobody watching. The loop also polls its parent pid."""
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class StatusAuth:
    """Who may be served on the status address: with an HMAC ``key`` only a request that carries
    its MAC (``mac``), a time within the window (``ts``) and a nonce not seen before (``nonce``:
    remembered for twice the window, so a replay is refused); without one, every request.
    ``refused`` counts the requests turned away."""

    def __init__(self, key: bytes | None) -> None:
        self.key = key
        self.refused = 0
        self._nonces: dict[str, float] = {}

    def check(self, req: dict) -> str:
        """"" if the request may be served; why not otherwise (and counted in ``refused``)."""
        why = self._why_not(req)
        if why:
            self.refused += 1
        return why

    def _why_not(self, req: dict) -> str:
        if self.key is None:
            return ""
        from .status import AUTH_WINDOW_S, request_mac

        mac = req.get("mac")
        if not isinstance(mac, str):
            return "unauthenticated: this server wants requests signed with its HMAC key (status --config/--key-file)"
        if not hmac.compare_digest(mac, request_mac(self.key, req)):
            return "unauthenticated: bad MAC"
        now = time.time()
        ts = req.get("ts")
        if not isinstance(ts, (int, float)) or abs(now - ts) > AUTH_WINDOW_S:
            return "unauthenticated: request time outside the window (clocks apart, or replayed)"
        nonce = req.get("nonce")
        if not isinstance(nonce, str) or nonce in self._nonces:
            return "unauthenticated: nonce missing or replayed"
        for k in [k for k, t in self._nonces.items() if now - t > 2 * AUTH_WINDOW_S]:
            del self._nonces[k]
        self._nonces[nonce] = now
        return ""


# ------------------------------------------------------------------------------ supervisor
class Supervisor:
    """Starts the loop process and serves status; ``run()`` until the loop stops.

    Everything slow happens here, never in the loop: draining the rings of shared memory to the
    recording (``record``: an MCAP file, ``recording``), feeding the live view (``live``:
    ``HOST:PORT`` of a Foxglove WebSocket server, ``live``), answering ``hapticproxy status``.
    With ``transport.hmac_key_file`` set, every status request must carry its HMAC (``status``:
    stop and re-arm move a haptic device)."""

    # What start() opens and close() closes again (None before and after): the loop process, the
    # status socket, the recording and the live view.
    proc: mp.process.BaseProcess | None = None
    sock: socket.socket | None = None
    writer: McapRecorder | None = None
    live: LiveView | None = None

    def __init__(self, settings: cfgmod.Settings, *, record: str = "", duration_s: float | None = None,
                 ready_timeout_s: float = 600.0, naive: bool = False, live: str = "") -> None:
        self.settings = settings
        self.naive = naive
        self.device_info: dict | None = None
        self.duration_s = duration_s
        # Only a loop process that hangs while alive meets this: one that dies or fails is seen
        # at once, and a stop at any moment is honoured. A first start with an empty kernel cache
        # on a busy 2-core machine compiles ~80 kernels for two minutes or more (CI of 3f9e6ba:
        # stopped by the old 120 s while still compiling), so the bound is generous.
        self.ready_timeout_s = ready_timeout_s
        rows = max(1024, int(settings["telemetry"]["ring_s"] * settings.rate_hz))
        self.ring_rows = rows
        self.shared = SharedState.create(rows)
        self.record = record or settings["telemetry"]["record"]
        #: what named the recording's path, for a message about it
        self.record_source = "--record" if record else "telemetry.record"
        self.live_address = live
        self._stop_requested = False
        self._trans_seq = 0
        self._contact_seq = 0
        self._last_contacts = None  # the newest contact-ring row read: (header, key, pos, normal, sep)
        self._last_transition = None
        self._tool_seq = 0          # the engaged tool last read from the shared block
        self.tool_shape = None      # the newest engaged client's tool (scene.ToolShape)
        self.auth = StatusAuth(self._hmac_key())
        self.exit_code = 0
        self._closed_shared = False
        # the loop's clock is CLOCK_MONOTONIC; recordings carry Unix time
        self._epoch_offset_ns = time.time_ns() - time.monotonic_ns()

    def _hmac_key(self):
        path = self.settings["transport"]["hmac_key_file"]
        if not path:
            return None
        from ..protocol.session import load_hmac_key

        return load_hmac_key(path)

    def start(self) -> bool:
        """Bind the status address, start the loop process and wait until it is ready (serving
        status meanwhile). ``False`` when a stop was requested during start-up (the loop process
        is stopped then, cleanly); :class:`StartupError` (one line, naming the address or what
        failed) when the server cannot start."""
        if self._stop_requested:  # a Ctrl-C before anything started: nothing to stop
            log.info("stopped during start-up")
            return False
        address = self.settings["status"]["address"]
        host, _, port = address.rpartition(":")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, int(port)))
        except OSError as exc:
            raise address_error("status.address", address, exc) from None
        self.sock.setblocking(False)
        if self.record:
            why = _check_writable(self.record, self.record_source, raise_=False)
            if why:  # the command line or the config must change
                raise StartupError(why, 2)
            from . import recording  # noqa: F401 - imported now, so the recording starts with the loop
        ctx = mp.get_context("spawn")
        reports, report = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=loop_process_main, name=LOOP_TITLE,
                                args=(self.settings, self.shared.name, self.ring_rows, self.auth.key, self.naive,
                                      report),
                                daemon=False)
        # The child starts with SIGINT blocked (a Ctrl-C while it imports would print a
        # traceback there); it ignores SIGINT, then unblocks it. The supervisor gets it meanwhile.
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            self.proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        report.close()  # the child holds its own end
        log.debug("loop process %d started", self.proc.pid)
        failure = None
        try:
            t_end = time.monotonic() + self.ready_timeout_s
            while self.shared.status[self._st("ready")] != 1.0:
                if self._stop_requested:
                    self._stop_during_startup()
                    return False
                failure = self._read_reports(reports, 0, failure)
                if not self.proc.is_alive():
                    self.proc.join(1)
                    failure = self._read_reports(reports, 0.5, failure)
                    if failure:
                        raise StartupError(*failure)
                    raise StartupError(f"the loop process exited during start-up (exit code {self.proc.exitcode})")
                if time.monotonic() > t_end:
                    raise StartupError("the loop process did not become ready in time")
                self._serve_status(0.02)
        finally:
            reports.close()
        if self.record:
            self.start_recording(self.record)
        if self.live_address:
            from .live import LiveView

            self.live = LiveView(self.live_address, self.settings, self.t0_epoch_ns)
            if self.tool_shape is not None:
                self.live.shape = self.tool_shape
        log.info("serving: %s at %.0f Hz, status on %s (rt scheduling: %s)%s%s", self.transport_url,
                 self.settings.rate_hz, "%s:%d" % self.sock.getsockname()[:2],  # the bound port, also for port 0
                 "yes" if self.shared.status[self._st("rt_scheduling")] else "no",
                 f", recording to {self.record}" if self.record else "",
                 f", live view on ws://{self.live.address}" if self.live else "")
        return True

    def _read_reports(self, reports, wait_s: float, failure):
        """Drain the loop process's reports: its device's info (kept for ``status``), or the one
        line that says why it cannot start (returned, raised once the process is gone)."""
        while reports.poll(wait_s):
            try:
                message, code = reports.recv()
            except EOFError:  # the loop process closed its end: nothing more to read
                break
            if message == DEVICE_INFO:
                self.device_info = code
                self._adopt_derived((code or {}).get("derived") or {})
            else:
                failure = (message, code)
        return failure

    def _adopt_derived(self, derived: dict) -> None:
        """The gains the loop lowered to what its device takes: the supervisor's settings (the
        recordings' config, ``status``) say what runs."""
        lowered = [tuple(x) for x in derived.get("lowered", ())]
        if not lowered:
            return
        data = copy.deepcopy(self.settings.data)
        for key, _was, now, _why in lowered:
            section, name = key.split(".")
            data[section][name] = now
        self.settings = dataclasses.replace(self.settings, data=data, lowered=self.settings.lowered + tuple(lowered))

    def _stop_during_startup(self) -> None:
        """Stop the loop process before it ever ran (it unwinds and closes its device at SIGTERM)."""
        log.info("stopping during start-up")
        self.proc.terminate()
        self.proc.join(10)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(2)
        self.exit_code = 0

    @property
    def t0_epoch_ns(self) -> int:
        """Unix time of the loop's start (its telemetry's ``t_s = 0``)."""
        return int(self.shared.status[self._st("t_start_ns")]) + self._epoch_offset_ns

    def _limits_published(self) -> bool:
        """The loop has published its status once since it started: the caps in the status block
        are its effective ones (the config's, lowered to the device's). Before that, some are
        still the zeros of a fresh block (issue 28: a recording's metadata said 0.0 N m)."""
        return float(self.shared.status[self._st("t_last_ns")]) > 0.0

    def _recording_meta(self) -> dict:
        """The recording's metadata: kinds, and the effective caps as the loop publishes them
        (``status --json`` reads the same fields); null while the loop has not published yet."""
        st = self.shared.status
        known = self._limits_published()

        def cap(name):
            return float(st[self._st(name)]) if known else None

        return {"device_kind": self.settings["device"]["kind"], "tool_kind": self.settings.tool_kind,
                "force_cap_n": cap("force_cap_n"), "torque_cap_n_m": cap("torque_cap_n_m"),
                "rate_limit_n_per_step": cap("rate_limit_n_per_step")}

    def start_recording(self, path: str) -> None:
        """Record from now on (the ring's rows from the current head) to the MCAP file ``path``."""
        head, chead = int(self.shared.head[0]), int(self.shared.contact_head[0])  # before the file opens
        from .recording import McapRecorder

        # the metadata record waits for the loop's first published status (service() writes it)
        self.writer = McapRecorder(path, rate_hz=self.settings.rate_hz, config=self.settings.as_dict(),
                                   t0_epoch_ns=self.t0_epoch_ns, flush_rows=self.settings["telemetry"]["flush_rows"],
                                   meta=self._recording_meta(), defer_meta=not self._limits_published(),
                                   shape=self.tool_shape)
        self.writer.start_at(head, chead, 0)
        self.record = str(path)

    @staticmethod
    def _st(name: str) -> int:
        from .shm import ST

        return ST[name]

    @property
    def transport_url(self) -> str:
        """The configured transport URL, with the port the loop bound where it was 0."""
        url = self.settings["transport"]["url"]
        port = int(self.shared.status[self._st("transport_port")])
        m = re.match(r"^(udp://.*):0$", url)
        return f"{m.group(1)}:{port}" if m and port > 0 else url

    def request_stop(self) -> None:
        if not self._stop_requested:
            self._stop_requested = True
            self.shared.request("stop")

    def run(self) -> int:
        t_end = None if self.duration_s is None else time.monotonic() + self.duration_s
        while self.proc.is_alive():
            self._serve_status(0.05 if self.live is None else self.live.period_s)
            self.service()
            if t_end is not None and time.monotonic() >= t_end:
                self.request_stop()
                t_end = None
        self.proc.join(5)
        self.service()
        code = int(self.shared.status[self._st("exit_code")])
        if self.proc.exitcode not in (0, None) and code == 0:
            code = 1
            log.error("the loop process died (exit code %s)", self.proc.exitcode)
        self.exit_code = code
        return code

    def service(self) -> None:
        """What the supervisor does between status requests: drain the recording, log the
        transitions, read the newest contacts, feed the live view."""
        if self.writer is not None:
            if not self.writer.meta_written and self._limits_published():
                self.writer.write_meta(self._recording_meta())
            self.writer.drain(self.shared)
        self._log_changes()
        items, self._contact_seq = self.shared.contact_rows_since(self._contact_seq)
        if items:
            self._last_contacts = items[-1]
        self._take_tools()
        if self.live is not None:
            self.live.publish(self.shared, self._last_contacts, self._last_transition)

    def _take_tools(self) -> None:
        """The engaged client's tool, which the loop writes into the shared block at each
        engagement (``SharedState.publish_tool``): the views draw the proxy with the newest one."""
        got = self.shared.engaged_tool()
        if got is None or got[0] == self._tool_seq:
            return
        from ..protocol.vocab import TOOL_KIND_NAMES
        from .scene import ToolShape

        seq, kind, mass, com, inertia = got
        self._tool_seq = seq
        self.tool_shape = ToolShape.from_hello(TOOL_KIND_NAMES.get(kind, "?"), mass, com, inertia)
        if self.writer is not None:
            self.writer.set_shape(self.tool_shape)
        if self.live is not None:
            self.live.shape = self.tool_shape

    def _log_changes(self) -> None:
        """Log every transition the loop wrote since the last call, with its reason."""
        for seq, t_ns, frm, to, reason, detail in self.shared.transitions_since(self._trans_seq):
            self._trans_seq = seq
            name = (lambda i: LOOP_STATES[i] if 0 <= i < len(LOOP_STATES) else str(i))
            level = logging.ERROR if name(to) == "fault" else logging.INFO
            text = describe(reason, detail)
            log.log(level, "loop %s -> %s: %s", name(frm), name(to), text)
            try:
                why = Reason(int(reason)).name.lower()
            except ValueError:
                why = str(reason)
            t0 = self.shared.status[self._st("t_start_ns")]
            self._last_transition = {"seq": seq, "t_s": (t_ns - t0) * 1e-9 if t0 else None, "from": name(frm),
                                     "to": name(to), "reason": why, "detail": detail, "text": text}

    def _serve_status(self, timeout_s: float) -> None:
        r, _, _ = select.select([self.sock], [], [], timeout_s)
        if not r:
            return
        for _ in range(64):
            try:
                data, addr = self.sock.recvfrom(4096)
            except BlockingIOError:
                return
            try:
                req = json.loads(data.decode() or "{}")
                if not isinstance(req, dict):
                    raise ValueError
            except ValueError:
                self._reply({"error": "request must be a JSON object"}, addr)
                continue
            why = self.auth.check(req)
            if why:
                self._reply({"error": why}, addr)
                continue
            try:
                reply = self.handle(req)
            except Exception as exc:  # noqa: BLE001 - a bad request never takes the supervisor down
                log.exception("status request %r failed", req.get("cmd"))
                reply = {"error": f"{type(exc).__name__}: {exc}"}
            self._reply(reply, addr)

    def _reply(self, obj: dict, addr) -> None:
        try:
            self.sock.sendto(dumps(obj).encode()[:65000], addr)
        except OSError:
            pass

    def status(self) -> dict:
        """The status reply: the loop's figures, the newest pose, command and contacts, the last
        transition, the recording and the live view."""
        from .lifecycle import Fault

        snap = self.shared.snapshot()
        snap["telemetry_file"] = str(self.record) if self.record else ""
        snap["telemetry_rows_written"] = self.writer.rows_written if self.writer else 0
        snap["telemetry_rows_lost"] = self.writer.rows_lost if self.writer else 0
        snap["config_source"] = self.settings.source
        snap["url"] = self.settings["transport"]["url"]
        derived = (self.device_info or {}).get("derived") or {}
        snap["outside_stable_region"] = [f"{k}: {why}" for k, why in self.settings.outside_stable_region] + [
            f"{k}: {why}" for k, why in derived.get("outside", ())]
        snap["lowered"] = [f"{k} {was:g} -> {now:.6g}: {why}" for k, was, now, why in derived.get("lowered", ())]
        snap["device_kind"] = self.settings["device"]["kind"]
        snap["device_info"] = self.device_info
        snap["tool_kind"] = self.settings.tool_kind
        snap["live"] = f"ws://{self.live.address}" if self.live else ""
        snap["authenticated"] = self.auth.key is not None
        span = ((snap["t_last_ns"] or 0) - (snap["t_start_ns"] or 0)) * 1e-9
        snap["achieved_rate_hz"] = (snap["steps"] - 1) / span if span > 0 and snap["steps"] > 1 else 0.0
        try:
            snap["fault_name"] = Fault(snap["fault"]).name.lower()
        except ValueError:
            snap["fault_name"] = str(snap["fault"])
        from .devices.base import DEV_FAULT_NAMES

        snap["device_fault_name"] = DEV_FAULT_NAMES.get(snap["device_fault"], str(snap["device_fault"]))
        snap["last_transition"] = self._last_transition
        shape = self.tool_shape
        snap["tool_shape"] = [[list(c), list(q), list(s)] for c, q, s in shape.boxes] if shape else None
        snap["tool_shape_source"] = shape.source if shape else None
        row = self.shared.latest_row()
        if row is not None:
            snap["latest"] = {"t_s": float(row["t_s"]), "device_pose": row["dev"][:7].tolist(),
                              "device_twist": row["dev"][7:].tolist(), "proxy_pose": row["proxy"][:7].tolist(),
                              "proxy_twist": row["proxy"][7:].tolist(), "command": row["cmd"].tolist(),
                              "environment_wrench": row["env"].tolist()}
        else:
            snap["latest"] = None
        c = self._last_contacts
        if c is not None:
            hdr, _key, pos, nrm, sep = c
            snap["last_update"] = {"t_s": float(hdr["t_s"]), "count": int(hdr["count"]),
                                   "min_separation_m": float(sep.min()) if len(sep) else None,
                                   "penetration_m": max(0.0, -float(sep.min())) if len(sep) else 0.0,
                                   # the contacts themselves, for a 3-D view (`hapticproxy view`)
                                   "position_m": pos.tolist(), "normal": nrm.tolist(), "separation_m": sep.tolist()}
        else:
            snap["last_update"] = None
        return snap

    def handle(self, req: dict) -> dict:
        cmd = req.get("cmd", "status")
        if cmd == "status":
            return self.status()
        if cmd == "rearm":
            return {"ok": True, "rearm": self.shared.request("rearm")}
        if cmd == "stop":
            self.request_stop()
            return {"ok": True}
        if cmd == "reset_stats":
            return {"ok": True, "reset": self.shared.request("reset_stats")}
        if cmd == "dump":
            from .recording import dump_ring

            path = req.get("path")
            if not isinstance(path, str) or not path:
                return {"error": "dump needs a path"}
            why = _check_writable(path, "dump", raise_=False)
            if why:
                return {"error": why}
            try:
                n = dump_ring(self.shared, path, rate_hz=self.settings.rate_hz, config=self.settings.as_dict(),
                              t0_epoch_ns=self.t0_epoch_ns, meta=self._recording_meta(), shape=self.tool_shape)
            except OSError as exc:
                return {"error": f"cannot write {path}: {exc.strerror}"}
            return {"ok": True, "rows": n, "path": path}
        return {"error": f"unknown cmd {cmd!r}"}

    def close(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.request_stop()
            self.proc.join(self.settings["safety"]["fade_s"] + 5)
            if self.proc.is_alive():
                self.proc.terminate()
                self.proc.join(2)
        if self.writer is not None and self._closed_shared is False:
            self.writer.write_meta(self._recording_meta())  # if the loop never published: caps null
            self.writer.drain(self.shared)
        if self.writer is not None:
            self.writer.close()
        if self.live is not None:
            self.live.close()
            self.live = None
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        if not self._closed_shared:
            self.shared.close(unlink=True)
            self._closed_shared = True


def _check_writable(path: str, what: str, raise_: bool = True) -> str:
    """A recording's path must be absolute (it is resolved by whoever names it: the server's own
    working directory means nothing to a caller) in a directory that exists: the server never
    creates directories. Returns (or raises as RuntimeError) why not; "" when it is fine."""
    why = ""
    p = os.fspath(path)
    if not os.path.isabs(p) and what == "dump":
        why = f"{what}: {p!r} is not an absolute path (`hapticproxy status --dump` sends one)"
    elif os.path.isdir(p):
        why = f"{what}: {p!r} is a directory"
    elif not os.path.isdir(os.path.dirname(os.path.abspath(p))):
        why = f"{what}: the directory of {p!r} does not exist (the server creates none)"
    if why and raise_:
        raise RuntimeError(why)
    return why


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="hapticproxy serve", description="Run the haptics server daemon.",
        epilog="Exit status: 0 after a clean stop (Ctrl-C, SIGTERM, `status --stop`, --duration; during start-up "
               "too), 1 a run-time failure (the transport or status address is taken, the loop process failed), "
               "2 a bad option, config key or value, or an address this machine does not have.")
    p.add_argument("--config", help="TOML scene/config file (defaults: loopback UDP, simulated planar device)")
    p.add_argument("--preset", choices=list(cfgmod.PRESETS),
                   help="speed/accuracy preset; wins over the file's preset and over the keys the preset sets "
                        "(loop.rate_hz, model.capacity, model.epsilon_m) even where the file pins them")
    p.add_argument("--url", help="transport URL clients connect to (overrides transport.url)")
    p.add_argument("--status", help="status address HOST:PORT (overrides status.address)")
    p.add_argument("--rate", type=float, help="haptic rate in Hz (overrides loop.rate_hz)")
    p.add_argument("--record", default="", metavar="FILE.mcap",
                   help="record telemetry, contacts and transitions to this MCAP file (Foxglove, PlotJuggler)")
    p.add_argument("--live", nargs="?", const="127.0.0.1:8765", default="", metavar="HOST:PORT",
                   help="serve a live view (Foxglove WebSocket protocol; default 127.0.0.1:8765)")
    p.add_argument("--duration", type=float, help="stop cleanly after this many seconds")
    p.add_argument("--print-config", action="store_true",
                   help="print every key in effect (the device's and the hand's too) as TOML and exit")
    p.add_argument("-q", "--quiet", action="count", default=0, help="fewer log lines (warnings and errors only)")
    args = p.parse_args(argv)
    # The command line's own SIGINT handler (``hapticproxy.cli.EarlyInterrupt``) records a Ctrl-C
    # that came while Python imported the server; it stays in place until the supervisor's own
    # handler replaces it below, which then honours what it recorded.
    early = signal.getsignal(signal.SIGINT)
    from ..protocol import logs

    logs.configure(logging.INFO, quiet=args.quiet)
    over: dict = {}
    if args.preset:
        over["preset"] = args.preset
    if args.url:
        over.setdefault("transport", {})["url"] = args.url
    if args.status:
        over.setdefault("status", {})["address"] = args.status
    if args.rate is not None:
        over.setdefault("loop", {})["rate_hz"] = args.rate
    try:
        settings = cfgmod.load(args.config, over)
        if args.print_config:
            print(settings.to_toml(), end="")
            return 0
        set_process_title(" ".join(["hapticproxy serve", *(argv if argv is not None else sys.argv[1:])]))
        _check_device(settings)
    except cfgmod.ConfigError as exc:
        print(f"hapticproxy serve: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"hapticproxy serve: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C before anything runs: nothing to stop
        log.info("stopped during start-up")
        return 0
    warn_outside_stable_region(settings)
    record = os.path.abspath(args.record) if args.record else ""
    # From here a signal asks the supervisor for a clean stop (during start-up too: the loop
    # process is stopped before it runs); held back while the supervisor is being built.
    signals = {signal.SIGINT, signal.SIGTERM}
    signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        sup = Supervisor(settings, record=record, duration_s=args.duration, live=args.live)

        def on_signal(signum, frame):  # noqa: ARG001
            sup.request_stop()

        for sig in signals:
            signal.signal(sig, on_signal)
        if getattr(early, "pending", False):  # Ctrl-C while starting: stop before the loop runs
            sup.request_stop()
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, signals)
    try:
        code = sup.run() if sup.start() else 0
    except StartupError as exc:
        print(f"hapticproxy serve: {exc}", file=sys.stderr)
        code = exc.code
    except RuntimeError as exc:
        print(f"hapticproxy serve: {exc}", file=sys.stderr)
        code = 1
    finally:
        sup.close()
    if code == 0:
        log.info("stopped cleanly")
    return code


def warn_outside_stable_region(settings: cfgmod.Settings) -> None:
    """Log every setting accepted outside the measured stable region (the research override)."""
    for key, why in settings.outside_stable_region:
        log.warning("OUTSIDE THE STABLE REGION (safety.allow_outside_stable_region = true): %s: %s", key, why)


def _check_device(settings: cfgmod.Settings) -> None:
    """Build the device once in the supervisor so a bad [device] table, or a gain the device
    cannot take (``devices/safe.py``), fails before any process starts."""
    from .devices import safe
    from .devices.base import load_device

    dev = load_device(settings["device"]["driver"], dict(settings["device"]), period_s=settings.period_ns * 1e-9)
    try:
        # a linkage tool runs on the device kind the config names (planar or spatial)
        want = settings["device"]["kind"] if settings.tool_kind == "linkage" else settings.tool_kind
        if dev.kind != want:
            raise cfgmod.ConfigError("device.kind", f"driver built a {dev.kind} device, config says {want}")
        safe.derive(settings, dev.info)  # (the loop process derives them again, and logs what it changed)
    finally:
        dev.close()
