"""The haptic loop: the tick on a fixed-rate schedule, and the Python around it, in parts.

``HapticLoop`` knows no engine and no particular device: it owns a transport (any backend), a
device driver, the controller/safety arrays and, once a client has engaged it, a ``LocalModel``
built from the client's ``Hello``. Its parts, one owner each (``docs/architecture.md``):

- the **tick** (``tick.py``): device read, controller, model step, safety filter, device write,
  accounting, as one compiled call over named arrays (``tick.TickArrays``, bound by
  :meth:`HapticLoop.bind` whenever the engaged model changes); who calls it: the compiled loop
  that owns the clock (``tick.run_ticks``), a device's servo thread (``servo.py``), or
  :meth:`HapticLoop.step` in simulated time;
- the **lifecycle** (``loop_lifecycle.Lifecycle``, ``loop.life``): states, transitions, the fault
  policy, stalls;
- the **protocol side** (``protocol_side.ProtocolSide``, ``loop.proto``): sessions, the engaged
  model, receiving, applying and acknowledging updates;
- the **status publisher** (``publisher.StatusPublisher``, ``loop.publisher``).

Each step: the tick first after the deadline (the device sampled and commanded), then its Python
part (:meth:`HapticLoop._service`): the lifecycle's reaction to the tick's results, the protocol
side's stages (acknowledge, apply, read the transport: each in its own step), the environment's
silence, and every 10 ms housekeeping (session timers, the supervisor's requests, stall recovery,
publishing the status). The compiled loop runs the steps that need no Python by itself.

Extension points: a device (``devices/base.DeviceDriver``: its ``tick_arrays`` for a simulated one,
``servo_io`` for one that owns the clock, plain ``read`` / ``write`` otherwise; a workspace
mapping around any of them, ``devices/mapped.MappedDevice``, runs inside the tick), a controller
(``control.CONTROLLERS``, inside the tick), a passivity layer (between the controller's command
and the safety filter in ``control._command_out``; the energy ledger at the port is
``control.port_energy``), a second device (a second ``TickArrays`` and tick: not built yet).
"""
from __future__ import annotations

import logging
import os
import time

import numpy as np

from . import control as ctl
from . import egress, ingest, tick
from .devices import safe
from .devices.base import DEV_FAULT_NAMES, DEV_NSTATE, DS_TIME, empty_state, load_device
from .devices.mapped import MappedDevice
from .devices.mapping import M_CMD, NM
from .lifecycle import LOOP_STATES, LS, Fault, Reason
from .loop_lifecycle import WD_OK, WD_SESSION_ENDED, WD_SILENT, Lifecycle  # noqa: F401 - re-exported
from .model.model import LinkSpec, LocalModel, ToolSpec, warm_up as model_warm_up
from .prediction import EngineAdvice, warm_up as advice_warm_up
from .protocol_side import (  # noqa: F401 - re-exported (the loop's public names before the split)
    ENV_RATE_WINDOW, POLL_BUDGET, ModelFactory, ProtocolSide, q_from_tool_pose, tool_from_hello,
)
from .publisher import StatusPublisher
from .readonly import frozen_copies
from .rings import account, record_contacts
from .shm import CT, ST, SharedState

#: steps housekeeping may wait for a step that handles no update (receives or applies one)
_HK_MAX_DEFER = 3
#: the tick's device arrays for a device that is not simulated, and its linkage arrays for a
#: rigid tool (never read: the same types as the real ones, so one compiled tick serves all)
_NO_SIM_DEVICE = (np.zeros(1), np.zeros(1), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64), np.zeros(1),
                  np.zeros((1, 1)), np.zeros(1), np.zeros(6))
_NO_LINKAGE = (np.zeros(8, dtype=np.int64), np.zeros((1, 1)), np.zeros((1, 1), dtype=np.int64), np.zeros((1, 1)))
#: datagrams start() discards at most (what a socket buffer holds of small ones)
_START_DRAIN_MAX = 100_000


class HapticLoop:
    """The server loop. It receives its parts built (``HapticLoop.build`` builds them from the
    settings) and checks at construction that they fit each other: the device's kind is the one
    the settings model, the controller was made for that device, the transport can be polled.
    ``run()``, or ``step()`` by hand in tests. Its state is the lifecycle's (``life``); its
    sessions and model the protocol side's (``proto``); the names of both read through it."""

    @classmethod
    def build(cls, settings, *, clock=None, transport=None, device=None, shared: SharedState | None = None,
              hmac_key: bytes | None = None, **kw) -> "HapticLoop":
        """Open what is not given (the transport at ``transport.url``, the ``[device]`` driver); the
        loop closes what it opened."""
        from ..protocol.transport import open_transport

        from .clock import MonotonicClock

        clock = clock or MonotonicClock()
        own_t = transport is None
        own_d = device is None
        if own_t:
            transport = open_transport(settings["transport"]["url"], "server")
        try:
            if own_d:
                device = load_device(settings["device"]["driver"], dict(settings["device"]),
                                     period_s=settings.period_ns * 1e-9, clock_ns=clock.now_ns)
            # the gains the device renders stably at this rate (devices/safe.py): defaults
            # lowered, a set value beyond them refused (ConfigError) unless the override is on
            derived = safe.derive(settings, device.info)
            safe.log_derived(settings, derived)
            loop = cls(derived, clock=clock, transport=transport, device=device, shared=shared, hmac_key=hmac_key,
                       **kw)
        except BaseException:
            if own_t:
                transport.close()
            if own_d and device is not None:
                device.close()
            raise
        loop._owns_transport, loop._owns_device = own_t, own_d
        return loop

    def __init__(self, settings, *, transport, device, clock=None, shared: SharedState | None = None,
                 endpoint=None, controller: ctl.Controller | None = None, models: ModelFactory | None = None,
                 hmac_key: bytes | None = None, max_packets_per_step: int = 32) -> None:
        from .clock import MonotonicClock

        self.settings = settings
        self.period_ns = settings.period_ns
        self.dt_s = self.period_ns * 1e-9
        self.clock = clock or MonotonicClock()
        self.kind = settings.tool_kind
        self.shared = shared or SharedState.local(max(16, int(settings["telemetry"]["ring_s"] * settings.rate_hz)))
        # the parts, checked against each other
        want = settings["device"]["kind"] if self.kind == "linkage" else self.kind
        if getattr(device, "kind", None) != want:
            raise ValueError(f"device: the loop models a {self.kind} tool on a {want} device, got a "
                             f"{getattr(device, 'kind', '?')} device")
        for name in ("recv_into", "send", "max_packet_bytes", "counters"):
            if not hasattr(transport, name):
                raise ValueError(f"transport: {type(transport).__name__} has no {name}")
        self.device = device
        # a workspace mapping (devices/mapping.py) runs inside the tick, on the array the
        # MappedDevice holds (its clutch's state included): the loop drives the driver under it
        # (its tick_arrays, servo_io or read / write) and the tick maps around that driver
        mapped = isinstance(device, MappedDevice)
        self._driver = device.inner if mapped else device
        self._map = device.mapping if mapped else np.zeros(NM)
        self._owns_transport = False
        self._owns_device = False
        self.ctrl = controller or ctl.Controller(settings, self.device.kind, self.device.limits)
        self.ctrl.set_moving_figures(getattr(self.device, "info", None))
        if self.ctrl.device_kind != self.device.kind:
            raise ValueError(f"controller: made for a {self.ctrl.device_kind} device, the device is {self.device.kind}")
        # a position frozen under force (devices.frozen): a driver that has the watch runs it on
        # its own raw readings (through a mapping too); the tick runs it for the rest, and for a
        # device whose servo thread runs the tick (its driver's read is not called then), on the
        # raw row before the mapping (a held clutch keeps the mapped row still on purpose) against
        # the force the device was written
        watch = getattr(self.device, "watch_frozen", None)
        if watch is not None:
            watch(settings["safety"]["frozen_s"], self.ctrl.frozen_force_n)
        self.ctrl.watch_frozen(watch is None)
        self.index_mapping = settings["controller"]["mapping"] == "index"
        self.dev = empty_state()
        self._stop_flag = False
        #: the supervisor's pid; when it changes (the supervisor died) the loop stops cleanly
        self.parent_pid = 0
        self._hk_n = 0
        #: beside a ticking thread: the passes Python took the tick's lock for (each may hold a tick)
        self.lock_passes = 0
        self._kernels_compiled = -1
        self._kernels: list = []
        self.dropped_at_start = 0  # datagrams that queued before start() (counted, not read)
        self.servo = None  # device-clocked: the servo callback's binding (``servo.ServoBinding``)
        #: a list: each Python-run step appends its tick's CPU time [ns] (``bench loop``); None: off
        self.tick_times = None
        self._st_missed = ST["missed_deadlines"]
        self.tk = tick.new_words(self.period_ns)
        self.life = Lifecycle(self)
        self.proto = ProtocolSide(self, transport=transport, endpoint=endpoint, models=models, hmac_key=hmac_key,
                                  max_packets_per_step=max_packets_per_step)
        self.publisher = StatusPublisher(self)
        self.ctrl.hold()  # nothing drives a proxy until a session engages
        # the tick's words and arrays (``tick.TickArrays``: bound again when the model changes)
        tk = self.tk
        tk[tick.TK_STALL_GAP_NS] = self.life.stall_gap_ns
        tk[tick.TK_HK_EVERY] = max(1, int(round(0.01 * settings.rate_hz)))
        tk[tick.TK_WATCHDOG_NS] = self.life.watchdog_ns
        tk[tick.TK_SIMULATED] = 1 if self.clock.simulated else 0
        tk[tick.TK_SIM_COST_NS] = int(getattr(self.clock, "step_cost_ns", 0))
        fileno = getattr(transport, "fileno", None)
        tk[tick.TK_FD] = fileno() if callable(fileno) else -1
        tk[tick.TK_STATE] = int(self.life.state)
        sim_arrays = getattr(self._driver, "tick_arrays", None)
        self._dev_arrays = sim_arrays() if callable(sim_arrays) else _NO_SIM_DEVICE
        self._io = tick.IO_SIM if callable(sim_arrays) else tick.IO_EXTERNAL
        tk[tick.TK_IO] = self._io
        tk[tick.TK_MAPPED] = 1 if mapped else 0
        #: what a driver in Python is written (IO_EXTERNAL): the tick's device command
        self._wcmd = self._map[M_CMD:M_CMD + 6] if mapped else self.ctrl.cmd
        self.bind()
        st = self.shared.status
        st[ST["period_ns"]] = self.period_ns
        st[ST["rate_hz"]] = settings.rate_hz
        st[ST["force_cap_n"]] = self.ctrl.force_cap_n
        st[ST["torque_cap_n_m"]] = self.ctrl.torque_cap_n_m
        st[ST["rate_limit_n_per_step"]] = self.ctrl.force_rate_n_per_step
        st[ST["loop_state"]] = self.life.state

    def bind(self) -> None:
        """The tick's arrays: the controller's, the device's, the engaged model's (or the idle
        dummy's), the shared rings'. Runs at construction and when the engaged model changes."""
        c, sh, tk, proto = self.ctrl, self.shared, self.tk, self.proto
        kind, par, st_, C, CI, cnt, wk = proto.kernel_args()
        largs = proto.linkage_args()
        lmeta, lk, lki, lw = largs if largs is not None else _NO_LINKAGE
        self._T = tick.TickArrays(c.cp, c.cs, c.cc, c.cmd, c.hand, c.R, c.c, self.dev, *self._dev_arrays,
                                  self._map, par, st_, C, CI, cnt, wk, lmeta, lk, lki, lw,
                                  sh.tel, sh.head, sh.hist_late, sh.hist_step, sh.stat, tk)
        # Python calls the tick through a descriptor of these arrays (one integer to pass, not
        # 32 arrays to unbox); the descriptor keeps the arrays it names referenced through _T
        self._desc = tick.descriptor(self._T)
        self._desc_addr = int(self._desc.__array_interface__["data"][0])
        tk[tick.TK_ACTIVE] = 0 if proto._margs is None else 1
        tk[tick.TK_LINKAGE] = 1 if largs is not None else 0
        tk[tick.TK_KIND] = int(kind)
        tk[tick.TK_UPD_DESC] = 0 if proto.model is None else proto.model.slot_address

    _bind = bind  # (the name the parts used before the split)

    @property
    def t0_ns(self) -> int:
        """When the loop started (the telemetry's time 0)."""
        return int(self.tk[tick.TK_T0_NS])

    @property
    def _last_write_ns(self) -> int:
        """The end of the last tick (its device write and accounting)."""
        return int(self.tk[tick.TK_LAST_WRITE_NS])

    @property
    def _deadline(self) -> int:
        return int(self.tk[tick.TK_DEADLINE_NS])

    @property
    def _t0(self) -> int:
        return self.t0_ns

    @property
    def _hk_every(self) -> int:
        """Ticks between housekeeping."""
        return int(self.tk[tick.TK_HK_EVERY])

    # ---------------------------------------------------------------------------- set-up
    def cold_kernels(self) -> list[str]:
        """The kernels :meth:`warm_up` will compile (nothing in numba's cache for them yet);
        a rigid tool's loop never calls the linkage step, so its missing cache is not counted."""
        from .warm import cold

        return [n for n in cold() if self.kind == "linkage" or n != ctl.haptic_step_linkage.py_func.__qualname__]

    def warm_up(self) -> None:
        """Compile/load every kernel this loop calls, with the argument types the loop passes, on
        throw-away arrays, before the first step: nothing may compile once deadlines are armed
        (a compile takes seconds; ``status.late_compiles`` counts any that still happens)."""
        model_warm_up()
        ingest.warm_up()
        egress.warm_up()
        advice_warm_up()
        s = self.settings
        c = ctl.Controller(s, self.device.kind, self.device.limits)
        dev_kind = self.device.kind
        tmp = LocalModel(ToolSpec.planar(1.0, 1e-3) if dev_kind == "planar" else
                         ToolSpec.one_dof(1.0) if dev_kind == "1dof" else ToolSpec.spatial(1.0, (1e-3,) * 3),
                         period_s=self.dt_s, capacity=4, warm=False)
        dev = empty_state()
        for active in (0, 1):
            for drive, slide in ((1.0, 1.0), (0.0, 0.0)):
                c.cs[ctl.CS_DRIVE] = drive
                c.cs[ctl.CS_SLIDE] = slide
                ctl.haptic_step(c.cp, c.cs, c.cc, dev, c.cmd, active, *tmp.kernel_args(), c.hand, c.R, c.c)
        if self.kind == "linkage":
            links = (LinkSpec(0.1, inertia_kg_m2=(1e-4, 1e-4, 1e-4)),
                     LinkSpec(0.1, (0.03, 0.0, 0.0), (1e-4, 1e-4, 1e-4), 0, "revolute", (0.0, 0.0, 1.0), (0.06, 0.0, 0.0)))
            lm = LocalModel(ToolSpec.linkage(links, 1, dev_kind == "planar"), period_s=self.dt_s, capacity=4, warm=False)
            kind_, par_, st_, C_, CI_, cnt_, wk_ = lm.kernel_args()
            for drive in (1.0, 0.0):
                c.cs[ctl.CS_DRIVE] = drive
                ctl.haptic_step_linkage(c.cp, c.cs, c.cc, dev, c.cmd, par_, *lm.linkage_args()[:3], st_, C_, CI_,
                                        cnt_, wk_, lm.linkage_args()[3], c.hand)
        ctl.fade_only(c.cp, c.cs, c.cc, c.cmd)
        c.grant(0.0)  # an engine's grant (ContactUpdate.work_on_tool_j), applied with an update
        c.cut()
        scratch = SharedState.local(4)  # the same views (so the same kernel types) as the shared block's
        account(scratch.tel, scratch.head, scratch.hist_late, scratch.hist_step, scratch.stat, self.period_ns, 1, 1,
                0, self.life.state, self.proto.updates, c.cs, self.proto.no_cnt, dev, c.cmd)
        record_contacts(scratch.contacts, 0.0, 0.0, 1, 1,  # the decoder's views, as _on_update records them
                        *frozen_copies(np.zeros((4, 3), dtype=np.int64), np.zeros((4, 3)), np.zeros((4, 3)),
                                       np.zeros(4)))
        ctl.proxy_hand_state(tmp.kind, tmp.kernel_args()[1], tmp.kernel_args()[2], c.R, c.c, self.proto._scratch_pose, 0)
        pose = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
        pose.flags.writeable = False  # what the decoder hands out: read-only views of the packet
        joints = np.zeros(2)
        joints.flags.writeable = False
        for qk in ctl.Q_KINDS.values():
            ctl.tool_q_from_pose(qk, pose, np.zeros(3), np.array([1.0, 0.0, 0.0]), joints, np.zeros(9))
            ctl.tool_q_from_pose(qk, pose, np.zeros(3), np.array([1.0, 0.0, 0.0]), self.proto._no_joints, np.zeros(9))
        adv_a, adv_p = EngineAdvice(0.01).kernel_arrays
        for sep in (joints, joints[:0]):  # the update's separation column: read-only, empty or not
            ctl.ack_state(tmp.kind, tmp.kernel_args()[1], tmp.kernel_args()[2], c.R, c.c, self.proto._scratch_pose, adv_a,
                          adv_p, 0.0, pose, sep)
        # the tick and the compiled loop, with this loop's argument types, on throw-away arrays
        tk = tick.new_words(self.period_ns)
        tk[tick.TK_SIMULATED] = 1
        tk[tick.TK_IO] = self._io
        tk[tick.TK_MAPPED] = self.tk[tick.TK_MAPPED]
        Tw = tick.TickArrays(c.cp, c.cs, c.cc, c.cmd, c.hand, c.R, c.c, dev, *(a.copy() for a in self._dev_arrays),
                             self._map.copy(), *tmp.kernel_args()[1:], *(a.copy() for a in _NO_LINKAGE), scratch.tel,
                             scratch.head, scratch.hist_late, scratch.hist_step, scratch.stat, tk)
        dw = tick.descriptor(Tw, check=True)
        tick.descriptor(self._T, check=True)  # the loop's own arrays: the types the reader builds
        tick.tick_at(dw.ctypes.data, 0, 0)
        tk[tick.TK_STOP] = 1
        tick.run_ticks_at(dw.ctypes.data)
        if self.clock_thread or self.device_clocked:
            from . import servo

            blk = np.zeros(servo.NSB, dtype=np.int64)
            blk[servo.SB_TK] = tk.ctypes.data
            blk[servo.SB_DESC] = dw.ctypes.data
            if self.clock_thread:
                servo.run_clock(blk)  # the clock thread's loop (its body never runs: SB_RUN is 0)
            servo.lock_between_ticks(tk, blk, 0, 0)  # the Python side's lock
            servo.unlock(tk)
            servo.lock(tk)  # (taken as the thread starts and at the stop: a compile there is a stall)
            servo.unlock(tk)
        warm = getattr(self.device, "warm_up", None)
        if callable(warm):
            warm()
        if self.device_clocked:  # the servo callback and the device's C functions (cfuncs: compiled at import)
            self._driver.servo_io()
        self._kernels = package_kernels()
        self._kernels_compiled = sum(len(d.overloads) for d in self._kernels)

    def start(self) -> None:
        """Drop what queued while the loop was built and warmed, arm the device and set the first
        deadline one period from now."""
        # Datagrams that waited through the warm-up (a cold cache: a minute) are stale: a client
        # retried its Hello since, maybe from another socket, and a session opened for an old one
        # would hold the slot for a peer that is gone (the client would hear SERVER_FULL).
        tr, buf = self.proto.transport, self.proto.rxbuf
        for _ in range(_START_DRAIN_MAX):
            if tr.recv_into(buf)[1] is None:
                break
            self.dropped_at_start += 1
        self.device.enable()
        now = self.clock.now_ns()
        tk = self.tk
        tk[tick.TK_T0_NS] = now
        tk[tick.TK_DEADLINE_NS] = now + self.period_ns
        tk[tick.TK_LAST_WRITE_NS] = now
        self.life.ontime_since = now
        if self._kernels_compiled < 0:
            self._kernels = package_kernels()
            self._kernels_compiled = sum(len(d.overloads) for d in self._kernels)
        st = self.shared.status
        st[ST["t_start_ns"]] = now
        self.life.transition("idle", Reason.START)
        st[ST["ready"]] = 1.0

    # ---------------------------------------------------------------------------- the step
    def step(self) -> bool:
        """One haptic step: wait for the deadline, then :meth:`step_at`. Returns ``False`` once
        the loop has stopped."""
        tk = self.tk
        deadline = int(tk[tick.TK_DEADLINE_NS])
        wake = self.clock.wait_until(deadline)
        late = wake - deadline
        period = self.period_ns
        if late >= period:  # missed whole periods: skip them rather than burst
            missed = late // period
            self.shared.status[self._st_missed] += missed
            tk[tick.TK_DEADLINE_NS] = deadline + (missed + 1) * period
            self.ctrl.skip(missed)  # fades and ramp-ins keep their times, not their step counts
        else:
            tk[tick.TK_DEADLINE_NS] = deadline + period
        return self.step_at(wake, late)

    def step_at(self, wake: int, late: int) -> bool:
        """The step woken at ``wake``: the tick first (device read, controller and model, safety
        filter, device write, accounting: ``tick.tick``, one compiled call), then what needs
        Python (faults, the lifecycle, the protocol: an update to acknowledge, one to apply,
        datagrams to read, housekeeping), so the device is sampled and commanded right after the
        deadline whatever the protocol costs. Returns ``False`` once the loop has stopped."""
        clock = self.clock
        tk = self.tk
        self.life.see_wake(wake, int(tk[tick.TK_LAST_WRITE_NS]))
        if self.proto._pending is None and self.proto._staged is None:
            # before the tick (a comparison): the step the environment's silence passes its
            # watchdog is the first that fades (an update waiting to be applied is not silence)
            self.life.check_silence(wake)
        # 1: the tick
        if self._io == tick.IO_EXTERNAL:
            tk[tick.TK_EXT_RC] = self._driver.read(self.dev)
            rcs = tick.tick_at(self._desc_addr, wake, late)
            rc_w = self._driver.write(self._wcmd)
            if rc_w:
                rcs |= (rc_w & 0xFF) << 16
            if clock.simulated:
                clock.charge()
            # a driver in Python: its write ends the step (the tick accounted up to its call)
            tk[tick.TK_LAST_WRITE_NS] = clock.now_ns()
        elif self.tick_times is None:
            rcs = tick.tick_at(self._desc_addr, wake, late)
            if clock.simulated:
                clock.charge()
        else:  # ``bench loop``: the tick's own CPU time, apart from the Python part of the step
            c0 = time.thread_time_ns()
            rcs = tick.tick_at(self._desc_addr, wake, late)
            self.tick_times.append(time.thread_time_ns() - c0)
            if clock.simulated:
                clock.charge()
        self.life.after_tick(rcs, wake)
        self._service(wake)
        return not self.stopped

    def _service(self, wake: int) -> None:
        """The step's Python part, after the tick: take the tick's result for the update it
        applied and acknowledge it, then stage the one received before for the next tick
        (:meth:`ProtocolSide.exchange`), then the transport, housekeeping (not in a step that
        was busy with an update, unless updates arrive in every step)."""
        proto = self.proto
        busy = proto.exchange(wake)
        if proto.poll(wake):
            busy = True
        # a step of Python's own for an update waiting (the tick applies a staged one by itself)
        self.tk[tick.TK_NEEDS_PYTHON] = 1 if proto._pending is not None else 0
        self._maybe_housekeeping(busy)

    def _maybe_housekeeping(self, busy: bool) -> None:
        """Housekeeping every ``TK_HK_EVERY`` ticks, not in a step that received or applied an
        update (each costs some us, as housekeeping does) unless updates arrive in every step (a
        flood): then at most ``_HK_MAX_DEFER`` steps late."""
        tk = self.tk
        tk[tick.TK_HK_COUNT] += 1
        n = int(tk[tick.TK_HK_COUNT])
        every = int(tk[tick.TK_HK_EVERY])
        if n >= every and (not busy or n >= every + _HK_MAX_DEFER):
            tk[tick.TK_HK_COUNT] = 0
            self._housekeeping(self.clock.now_ns())

    # ---------------------------------------------------------------------------- housekeeping
    def _housekeeping(self, now: int) -> None:
        """Every 10 ms: the session timers, the lifecycle's checks, the supervisor's requests, the
        late-compile count, the status (beside a ticking thread the same two halves run apart:
        :meth:`_housekeeping_locked` with the tick's lock, :meth:`_housekeeping_unlocked` after)."""
        self.proto.endpoint.poll(now)
        self._housekeeping_locked(now)
        self._housekeeping_unlocked(now)

    def _count_late_compiles(self) -> None:
        self._hk_n += 1
        if self._hk_n % 100 == 0 and self._kernels_compiled >= 0:
            # about once a second: a kernel compiled after warm-up stalls the loop for seconds;
            # counted so a test (and a person reading status) sees that warm-up missed one
            n = 0
            for d in self._kernels:  # the dispatchers found at warm-up: a few us, no module scan
                n += len(d.overloads)
            if n > self._kernels_compiled:
                self.shared.status[ST["late_compiles"]] += n - self._kernels_compiled
                self._kernels_compiled = n

    # ---------------------------------------------------------------------------- running
    def run(self, *, max_steps: int | None = None, duration_s: float | None = None) -> None:
        """Step until stopped (or ``max_steps`` / ``duration_s`` of loop time, then stop cleanly).

        On the monotonic clock the compiled loop (``tick.run_ticks``) owns the clock and ticks by
        itself, handing back only the steps and the aftermath that need Python; on any other
        clock (simulated time, the naive baseline), or with a driver written in Python (read and
        written by Python), each step is :meth:`step`."""
        from .clock import MonotonicClock

        if type(self.clock) is MonotonicClock and self.device_clocked:
            self._run_device_clocked(duration_s)
        elif type(self.clock) is MonotonicClock and self.clock_thread:
            self._run_threaded(duration_s)
        elif type(self.clock) is not MonotonicClock or self._io == tick.IO_EXTERNAL:
            # (a driver in Python is read and written by Python every step)
            self._run_steps(max_steps, duration_s)
        else:
            self._run_compiled(max_steps, duration_s)
        self.publisher.publish(self.clock.now_ns())

    def _run_steps(self, max_steps, duration_s) -> None:
        end_ns = None if duration_s is None else self.clock.now_ns() + int(duration_s * 1e9)
        n = 0
        step = self.step
        while step():
            n += 1
            if (max_steps is not None and n >= max_steps) or (end_ns is not None and self._deadline >= end_ns):
                if not self.stopping:
                    self.request_stop()
                    # bounded: the fade takes fade_s; then one more step closes the sessions
                    max_steps = None
                    end_ns = None

    def _run_compiled(self, max_steps, duration_s) -> None:
        tk = self.tk
        # the spin never takes more than tick.SPIN_MAX_SHARE of the period (why: there)
        self._arm_spin()
        end_ns = None if duration_s is None else self.clock.now_ns() + int(duration_s * 1e9)
        n0 = int(tk[tick.TK_TICKS])
        steps = 0
        while not self.stopped:
            ev = tick.run_ticks_at(self._desc_addr)  # (an engagement binds a new descriptor)
            if ev == tick.EV_STEP:
                self.step_at(int(tk[tick.TK_WAKE_NS]), int(tk[tick.TK_LATE_NS]))
                steps += 1
            elif ev == tick.EV_TICKED:
                self._after_compiled_tick()
            else:
                tk[tick.TK_STOP] = 0
                self._stop_flag = True
                self._housekeeping(self.clock.now_ns())
            n = steps + int(tk[tick.TK_TICKS]) - n0
            if (max_steps is not None and n >= max_steps) or (end_ns is not None and self._deadline >= end_ns):
                if not self.stopping:
                    self.request_stop()
                max_steps = None
                end_ns = None

    def _arm_spin(self) -> None:
        """The compiled wait's spin before each deadline: the calibrated one, at most
        ``tick.SPIN_MAX_SHARE`` of the period (why: there)."""
        self.tk[tick.TK_SPIN_NS] = min(int(self.clock.spin_ns), int(self.period_ns * tick.SPIN_MAX_SHARE))
        self.shared.status[ST["spin_ns"]] = float(self.tk[tick.TK_SPIN_NS])

    @property
    def device_clocked(self) -> bool:
        """The device owns the clock (its SDK's servo thread runs the tick: ``server/servo.py``),
        through a workspace mapping too (the tick maps)."""
        info = getattr(self.device, "info", None)
        return getattr(info, "clock", "loop") == "device" and callable(getattr(self._driver, "servo_io", None))

    def _run_device_clocked(self, duration_s) -> None:
        """The tick runs in the device's servo thread (``servo.SERVO_CALLBACK``); this thread runs
        the rest beside it (:meth:`_serve_beside`). The tick's results accumulate in
        ``TK_RC_STICKY`` until taken here."""
        from .servo import SERVO_CALLBACK, ServoBinding, lock, unlock

        tk = self.tk
        io = self._driver.servo_io()
        rate = getattr(self.device.info, "native_rate_hz", None) or self.settings.rate_hz
        binding = ServoBinding(int(round(1e9 / rate)), io["begin"], io["end"], io["ctx"])
        lock(tk)
        try:
            self._io = tick.IO_NATIVE
            tk[tick.TK_IO] = tick.IO_NATIVE
            tk[tick.TK_NATIVE_READ] = io["read"]
            tk[tick.TK_NATIVE_WRITE] = io["write"]
            tk[tick.TK_NATIVE_CTX] = io["ctx"]
            tk[tick.TK_SIMULATED] = 0
            self.ctrl.watch_frozen(True)
            binding.bind(self._T)
        finally:
            unlock(tk)
        self.servo = binding
        self._driver.schedule(SERVO_CALLBACK, binding.address)
        try:
            self._serve_beside(binding, duration_s)
        finally:
            self._driver.schedule_python()  # the servo thread must not reach arrays freed after this

    @property
    def clock_thread(self) -> bool:
        """``[loop] protocol_thread`` on a device the tick reaches by itself (the simulated one,
        ``IO_SIM``): the tick runs in a clock thread of its own (:meth:`_run_threaded`). "auto":
        when this process may run on two CPUs or more (on one, the Python thread waiting for the
        gap after a tick would keep the clock thread, of the same real-time priority, off it)."""
        want = self.settings["loop"]["protocol_thread"]
        if want == "auto":
            want = len(os.sched_getaffinity(0)) >= 2 if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1) >= 2
        return bool(want) and self._io != tick.IO_EXTERNAL

    def _run_threaded(self, duration_s) -> None:
        """The tick in a clock thread of its own (``servo.run_clock``: compiled, no GIL, absolute
        deadlines, never back in Python until the end); everything Python does runs on this
        thread, beside it (:meth:`_serve_beside`). What the tick must do at once it does in its
        own thread: a device fault's or a non-finite value's cut, a stall as long as the device's
        watchdog cut, the environment's silence starting the fade; Python names and classifies
        them at its next pass (within a millisecond)."""
        import threading

        from .clock import lower_fifo_priority, pin_to_cpu, set_fifo_priority
        from .servo import SB_CMD, SB_RUN, SB_TK, ServoBinding, lock, run_clock, unlock

        tk = self.tk
        binding = ServoBinding(self.period_ns)
        blk = binding.block
        blk[SB_TK] = tk.__array_interface__["data"][0]
        blk[SB_CMD] = self._wcmd.__array_interface__["data"][0]
        lock(tk)
        try:
            self._arm_spin()
            tk[tick.TK_DEV_WD_NS] = self.life.dev_wd_ns
            tk[tick.TK_STALL_SEEN] = 0
            tk[tick.TK_RC_STICKY] = 0
            now = self.clock.now_ns()
            if tk[tick.TK_DEADLINE_NS] < now:  # started a while ago (a test): not missed deadlines
                tk[tick.TK_DEADLINE_NS] = now + self.period_ns
                tk[tick.TK_LAST_WRITE_NS] = now
            binding.bind(self._T)
            blk[SB_RUN] = 1
        finally:
            unlock(tk)
        self.servo = binding
        cpu, others, saved = self._clock_cpus()

        def clock_main(blk):
            pin_to_cpu(cpu)  # this thread only
            run_clock(blk)

        clock = threading.Thread(target=clock_main, args=(blk,), name="hapticproxy-clock", daemon=True)
        clock.start()  # (it inherits this thread's scheduling: SCHED_FIFO when granted)
        lowered = lower_fifo_priority()  # one below the clock thread's (it inherited this one)
        try:
            self._serve_beside(binding, duration_s)
        finally:
            blk[SB_RUN] = 0
            clock.join()
            if lowered is not None:
                set_fifo_priority(lowered)
            if saved is not None:
                try:
                    os.sched_setaffinity(0, saved)
                except OSError:
                    pass
            self.shared.status[ST["clock_cpu"]] = -1.0

    def _clock_cpus(self):
        """``[loop] clock_cpu`` applied to this (the Python) thread: returns the clock thread's CPU
        (None: not pinned), the CPUs this thread now keeps to, and its affinity before (None when
        unchanged). The status says where the clock ticks; a CPU that cannot be had is logged."""
        from .clock import clock_cpus

        if not hasattr(os, "sched_setaffinity"):
            return None, None, None
        saved = os.sched_getaffinity(0)
        cpu, others, why = clock_cpus(self.settings["loop"]["clock_cpu"], saved)
        log = logging.getLogger("hapticproxy.loop")
        if why:
            log.warning("[loop] clock_cpu: %s; the clock thread is not pinned", why)
        if cpu is None:
            return None, None, None
        try:
            os.sched_setaffinity(0, others)
        except OSError as exc:
            log.warning("[loop] clock_cpu: the Python thread cannot keep off CPU %d (%s); not pinned", cpu, exc.strerror)
            return None, None, None
        self.shared.status[ST["clock_cpu"]] = float(cpu)
        return cpu, others, saved

    def _serve_beside(self, binding, duration_s) -> None:
        """Everything Python does while another thread ticks (a clock thread, a device's servo
        thread): wait on the socket, decode and check datagrams, hand updates over and send their
        acknowledgements (the update slot's handshake: no lock), keep the sessions' timers and
        publish the status without the tick's lock; take ``TK_LOCK`` only to change what the
        tick uses (:meth:`threaded_pass`: an engagement, a transition, a fault's cut,
        housekeeping's lifecycle part), in the gap after a tick with half a period ahead
        (``servo.lock_between_ticks``), so that this work ends before the next tick wants the
        lock. A tick that finds it held ticks nothing (a device's servo tick writes the previous
        command again) and counts itself held (``servo_held``)."""
        import select

        from .servo import SB_PERIOD_NS, lock, lock_between_ticks, unlock

        tk = self.tk
        blk = binding.block
        fd = int(tk[tick.TK_FD])
        proto = self.proto
        end_ns = None if duration_s is None else self.clock.now_ns() + int(duration_s * 1e9)
        hk_ns = int(tk[tick.TK_HK_EVERY]) * int(self.period_ns)
        next_hk = self.clock.now_ns() + hk_ns
        # the lock's work takes some us (an engagement milliseconds); waited for at most two
        # periods of the ticking thread (one held or stalled)
        room_ns = int(blk[SB_PERIOD_NS]) // 2
        patience_ns = 2 * int(blk[SB_PERIOD_NS])
        while not self.stopped:
            # wait for a datagram; while the tick has a staged update, a period at most (its
            # acknowledgement goes out as soon as it is applied)
            wait_s = self.dt_s if proto._staged is not None else 0.001
            if fd >= 0:
                readable = bool(select.select((fd,), (), (), wait_s)[0])
            else:
                time.sleep(wait_s)
                readable = True  # a transport without a socket is polled every millisecond
            now = self.clock.now_ns()
            if readable:
                proto.poll(now)  # decoded and checked beside the tick: the protocol's own state
            hk_due = now >= next_hk
            if hk_due:
                next_hk = now + hk_ns
                proto.endpoint.poll(now)  # the sessions' timers: the protocol's own state
            if end_ns is not None and now >= end_ns and not self.stopping:
                lock(tk)
                try:
                    self.request_stop()
                finally:
                    unlock(tk)
                end_ns = None
            proto.exchange(now, locked=False)
            tk[tick.TK_NEEDS_PYTHON] = 1 if proto.needs_lock else 0
            hk_locked = hk_due and self._housekeeping_needs_lock()
            if not python_has_work(tk, False, hk_locked):  # (the datagrams were read above, unlocked)
                if hk_due:
                    self._housekeeping_unlocked(now)
                continue
            lock_between_ticks(tk, blk, room_ns, patience_ns)
            self.lock_passes += 1
            try:
                now = self.clock.now_ns()
                self.threaded_pass(now, hk_locked)
                if self._T is not binding._keep[0]:
                    binding.bind(self._T)  # an engagement bound the tick to the new model's arrays
            finally:
                unlock(tk)
            if hk_due:
                self._housekeeping_unlocked(now)

    def threaded_pass(self, now: int, hk_due: bool) -> None:
        """What this thread does with the tick's lock held, beside a ticking thread: the tick's
        results (a fade it started, a stall it saw, faults), what the update's hand-over left for
        the lock (an engagement, a transition: :meth:`ProtocolSide.exchange`), housekeeping's
        lifecycle part."""
        tk = self.tk
        life = self.life
        rcs = int(tk[tick.TK_RC_STICKY])
        tk[tick.TK_RC_STICKY] = 0
        life.take_tick_fade(now)
        if tk[tick.TK_STALL_SEEN] != 0:
            tk[tick.TK_STALL_SEEN] = 0
            life.see_wake(int(tk[tick.TK_STALL_WAKE_NS]), int(tk[tick.TK_STALL_FROM_NS]))
        life.after_tick(rcs, now)
        # (the environment's silence is the tick's to judge: it starts the fade itself, counted
        # from the end of a stall it saw, and take_tick_fade above follows it; judged here too,
        # a stall whose end the tick had not reported yet would read as the engine's silence)
        if self.proto.needs_lock:
            self.proto.exchange(now)
            tk[tick.TK_NEEDS_PYTHON] = 0
        if hk_due:
            self._housekeeping_locked(now)

    def _housekeeping_needs_lock(self) -> bool:
        """Whether :meth:`_housekeeping_locked` has anything to do (a lifecycle check that may act,
        a supervisor's request, a parent gone): beside a ticking thread the lock is taken for
        housekeeping only then, not every 10 ms."""
        ctrl_ = self.shared.control
        return bool(self.life.has_housekeeping() or self._stop_flag
                    or (self.parent_pid and os.getppid() != self.parent_pid)
                    or ctrl_[CT["stop"]] != ctrl_[CT["stop_ack"]] or ctrl_[CT["rearm"]] != ctrl_[CT["rearm_ack"]])

    def _housekeeping_locked(self, now: int) -> None:
        """The part of :meth:`_housekeeping` that changes what the tick uses (the lifecycle's
        checks, the supervisor's requests), with a clock thread: run with the tick's lock held."""
        self.life.housekeeping(now)
        sh = self.shared
        ctrl_ = sh.control
        if self.parent_pid and os.getppid() != self.parent_pid:
            self._stop_flag = True
        if ctrl_[CT["stop"]] != ctrl_[CT["stop_ack"]] or self._stop_flag:
            ctrl_[CT["stop_ack"]] = ctrl_[CT["stop"]]
            self.request_stop()
        if ctrl_[CT["rearm"]] != ctrl_[CT["rearm_ack"]]:
            ctrl_[CT["rearm_ack"]] = ctrl_[CT["rearm"]]
            self.rearm()

    def _housekeeping_unlocked(self, now: int) -> None:
        """The rest of :meth:`_housekeeping` (statistics, the late-compile count, the status): the
        tick's arrays only read, as the status readers of other processes read them."""
        sh = self.shared
        ctrl_ = sh.control
        if ctrl_[CT["reset_stats"]] != ctrl_[CT["reset_ack"]]:
            ctrl_[CT["reset_ack"]] = ctrl_[CT["reset_stats"]]
            sh.hist_late[:] = 0
            sh.hist_step[:] = 0
            sh.status[ST["lateness_max_us"]] = 0.0
            sh.status[ST["compute_max_us"]] = 0.0
            sh.status[ST["overruns"]] = 0.0
            sh.status[ST["missed_deadlines"]] = 0.0
        self._count_late_compiles()
        self.publisher.publish(now)

    def _after_compiled_tick(self) -> None:
        """What a tick run by ``run_ticks`` left for Python: its results, a datagram, housekeeping."""
        tk = self.tk
        wake = int(tk[tick.TK_LAST_WRITE_NS])
        self.life.after_tick(int(tk[tick.TK_RC]), wake)
        proto = self.proto
        busy = proto.poll(wake)
        busy = proto.exchange(wake) or busy  # (staged now: the next tick applies it)
        tk[tick.TK_NEEDS_PYTHON] = 1 if proto._pending is not None else 0
        n = int(tk[tick.TK_HK_COUNT])
        every = int(tk[tick.TK_HK_EVERY])
        if n >= every and (not busy or n >= every + _HK_MAX_DEFER):
            tk[tick.TK_HK_COUNT] = 0
            self._housekeeping(self.clock.now_ns())

    def close(self) -> None:
        """Stop output and release what this loop opened."""
        try:
            self.device.disable()
        finally:
            if self._owns_device:
                self.device.close()
            if self._owns_transport:
                self.proto.transport.close()

    # ---------------------------------------------------------------------------- views
    def counters(self) -> dict:
        d = {
            "updates": self.updates, "acks": self.acks, "update_errors": self.update_errors,
            "engagements": self.engagements, "faults_total": self.faults_total,
            "dropped_at_start": self.dropped_at_start,
            "stall_trips": self.stall_trips, "stall_recoveries": self.stall_recoveries,
            "lock_passes": self.lock_passes,
            "state": self.state_name, "fault": Fault(self.fault).name.lower(),
            "device_fault": DEV_FAULT_NAMES.get(self.device_fault, str(self.device_fault)),
        }
        d.update({f"ctrl_{k}": v for k, v in self.ctrl.counters().items()})
        d.update({f"session_{k}": v for k, v in self.proto.endpoint.counters.as_dict().items()})
        return d

    @property
    def state_name(self) -> str:
        return LOOP_STATES[int(self.state)]

    def device_time_s(self) -> float:
        return float(self.dev[DS_TIME])

def python_has_work(tk, readable: bool, hk_due: bool) -> bool:
    """Beside a ticking thread (a clock thread, a device's servo thread): whether the Python
    thread takes the tick's lock now. Only when it has work (``readable``: a datagram to handle
    with the lock; housekeeping due, a tick's results or a stall it saw to take, an update that
    engages or brings a transition (``TK_NEEDS_PYTHON``; the others go through the update slot
    without the lock), a fade or a stop under way): each time it holds the lock, a tick may
    find it held (``servo_held``), and a loaded machine can preempt this thread while it holds it."""
    st = tk[tick.TK_STATE]
    return bool(readable or hk_due or tk[tick.TK_RC_STICKY] != 0 or tk[tick.TK_NEEDS_PYTHON] != 0
                or tk[tick.TK_STALL_SEEN] != 0 or st == tick._LS_FADING or st == tick._LS_STOPPING)


def package_kernels() -> list:
    """The numba dispatchers of every imported module of this package."""
    import sys

    from numba.core.registry import CPUDispatcher

    out = []
    for name, mod in list(sys.modules.items()):
        if not name.startswith("hapticproxy.") or mod is None:
            continue
        for obj in vars(mod).values():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name:
                out.append(obj)
    return out

def kernel_signatures() -> dict[str, int]:
    """Signatures compiled (or loaded) so far, per numba kernel of this package."""
    return {f"{d.py_func.__module__}.{d.py_func.__name__}": len(d.overloads) for d in package_kernels()}

def kernels_compiled() -> int:
    """Signatures compiled (or loaded) so far by every numba kernel of this package."""
    return sum(kernel_signatures().values())


def _delegate(part: str, *names: str) -> None:
    """``HapticLoop.<name>`` reads and writes ``HapticLoop.<part>.<name>`` (the names tests, the
    daemon and the benchmarks used before the loop was split into parts)."""
    for name in names:
        setattr(HapticLoop, name, property(lambda self, n=name: getattr(getattr(self, part), n),
                                           lambda self, v, n=name: setattr(getattr(self, part), n, v)))


_delegate("life", "state", "watchdog", "fault", "device_fault", "faults_total", "last_reason", "stall_trips",
          "stall_recoveries", "watchdog_ns", "stopping", "stopped")
_delegate("proto", "transport", "endpoint", "models", "server_config", "rxbuf", "model", "session_id", "com_m",
          "last_update_ns", "last_env_time_s", "env_rate_hz", "updates", "acks", "update_errors", "engagements",
          "advice", "poll_cut", "max_packets_per_step", "poll_budget_ns", "_pending", "_staged", "_apply_stage",
          "_margs", "_linkage", "_largs")
for _name, _method in (("transition", "transition"), ("rearm", "rearm"), ("request_stop", "request_stop"),
                       ("_after_fade", "after_fade"), ("_on_fault", "on_fault")):
    setattr(HapticLoop, _name, (lambda m: lambda self, *a, **k: getattr(self.life, m)(*a, **k))(_method))
for _name, _method in (("_survive", "survive"), ("_on_update", "on_update"), ("_ack", "ack"), ("_engage", "engage"),
                       ("_check_hello", "check_hello"), ("_poll", "poll"), ("_contacts", "contacts")):
    setattr(HapticLoop, _name, (lambda m: lambda self, *a, **k: getattr(self.proto, m)(*a, **k))(_method))
HapticLoop.publish = lambda self, now: self.publisher.publish(now)

__all__ = ["HapticLoop", "tool_from_hello", "q_from_tool_pose", "kernels_compiled", "DEV_NSTATE"]
