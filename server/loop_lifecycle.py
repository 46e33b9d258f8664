"""The loop's lifecycle part: the one owner of the loop's state, its faults and its stalls.

``Lifecycle`` changes the state only through :meth:`transition` (the table is
``lifecycle.TRANSITIONS``) and applies the fault policy (``lifecycle.FAULT_POLICY``: every source
of trouble, its output and how force comes back): a tick's results (:meth:`after_tick`), the
loop's own stalls (:meth:`see_wake`), the environment's silence (:meth:`check_silence`), what
housekeeping finds (:meth:`housekeeping`: stall recovery, a device link coming up, a session
that ended), a re-arm and a stop. It acts on the loop's other parts (the controller's gain and
hold, the device's enable, the protocol side's model) and on nothing per step.
"""
from __future__ import annotations

from . import control as ctl
from . import tick
from .devices.base import DEV_FAULT_LINK, DEV_FAULT_WATCHDOG
from .lifecycle import LOOP_STATES, LS, STALL_EXPLAINS_S, TRANSITIONS, Fault, Reason
from .shm import ST

WD_OK = 0
WD_SILENT = 1
WD_SESSION_ENDED = 2


class Lifecycle:
    """States, faults and stalls of one ``HapticLoop`` (its ``life``)."""

    def __init__(self, loop) -> None:
        self.loop = loop
        scfg = loop.settings["safety"]
        self.state = LS["starting"]
        self.watchdog = WD_OK
        self.fault = Fault.NONE
        self.device_fault = 0
        self.faults_total = 0
        self.last_reason = Reason.START
        #: the environment silent this long while engaged starts a fade
        self.watchdog_ns = int(scfg["watchdog_s"] * 1e9)
        # stalls: a late loop trips the device's own watchdog; it recovers once on time again
        self.dev_wd_ns = int(round(float(getattr(loop.device.limits, "watchdog_s", 0.0)) * 1e9))
        self._recover_ns = int(scfg["stall_recover_s"] * 1e9)
        self._stall_window_ns = int(scfg["stall_window_s"] * 1e9)
        self._stall_explains_ns = int(STALL_EXPLAINS_S * 1e9)
        self._stall_trips_max = int(scfg["stall_trips_max"])
        self._trip_times: list[int] = []
        #: a gap between two steps' device writes longer than this is a stall: half the device's
        #: own watchdog (a step late by a period or two threatens nothing; it is counted as a
        #: missed deadline, not as being off time)
        self.stall_gap_ns = max(2 * loop.period_ns, self.dev_wd_ns // 2 if self.dev_wd_ns > 0 else 25_000_000)
        self.stall_trips = 0
        self.stall_recoveries = 0
        self.stall_ns = 0         # the latest gap between steps longer than two periods
        self.stall_at = 0         # when it ended
        self.ontime_since = 0     # the end of the last stall
        self.speeding = False     # a speed trip while nothing was rendered is logged when it starts
        self.rendered_ever = False  # a session was ever engaged (force rendered, or ramping in)

    # ---------------------------------------------------------------------------- the state
    @property
    def stopping(self) -> bool:
        return self.state == LS["stopping"] or self.state == LS["stopped"]

    @property
    def stopped(self) -> bool:
        return self.state == LS["stopped"]

    def transition(self, to: str, reason: Reason, detail: float = 0.0) -> None:
        """Change state (``lifecycle.TRANSITIONS``), apply what the new state means for the force
        and the proxy, log it. Runs at events only (engagement, silence, faults), never per step."""
        lp = self.loop
        frm = LOOP_STATES[int(self.state)]
        if to not in TRANSITIONS[frm]:
            raise RuntimeError(f"haptic loop: no transition {frm} -> {to} ({Reason(reason).name})")
        c = lp.ctrl
        if to == "engaged":
            # the coupling's damping for this session's tool (a heavy one rests: control.fit_tool)
            model = lp.proto.model
            c.fit_tool(model.tool if model is not None else None)
            c.engage(slide=lp.index_mapping)
            self.rendered_ever = True
        else:
            c.hold()
            if lp.proto.model is not None:
                lp.proto.model.stop()  # held where it is: nothing pushes it while nothing is rendered
        if to == "idle":
            lp.proto.drop_model()
        if to == "fading":
            self.watchdog = WD_SILENT if reason == Reason.SILENT else WD_SESSION_ENDED
        elif to != "fault":
            self.watchdog = WD_OK
        self.state = LS[to]
        lp.tk[tick.TK_STATE] = int(self.state)
        self.last_reason = Reason(reason)
        sh = lp.shared
        sh.log_transition(lp.clock.now_ns(), LS[frm], self.state, int(reason), float(detail))
        # the state's why with it (the publisher's next pass is up to 10 ms away): a reader never
        # sees "fault" with no fault named
        sh.status[ST["fault"]] = self.fault
        sh.status[ST["device_fault"]] = self.device_fault
        sh.status[ST["loop_state"]] = self.state

    # ---------------------------------------------------------------------------- per step
    def see_wake(self, wake: int, last_write_ns: int) -> None:
        """The step woken at ``wake``: a gap since the last tick longer than ``stall_gap_ns`` is a
        stall (the process did not run: what the device saw, too)."""
        gap = wake - last_write_ns
        if gap > self.stall_gap_ns:
            self.stall_ns = gap
            self.stall_at = wake
            self.ontime_since = wake
            self.loop.proto.quiet_since()
            if gap >= self.dev_wd_ns > 0:
                self.on_own_stall(wake)

    def after_tick(self, rcs: int, wake: int) -> None:
        """What a tick's results ask: a fault, or a fade that reached zero."""
        if rcs:
            rc, rc_dev, rc_w = rcs & 0xFF, (rcs >> 8) & 0xFF, (rcs >> 16) & 0xFF
            self.on_fault(rc, rc_dev or rc_w, wake)
        elif self.speeding:
            self.speeding = False
        if (self.state == LS["fading"] or self.state == LS["stopping"]) and self.loop.ctrl.cs[ctl.CS_GAIN] <= 0.0:
            self.after_fade()

    def check_silence(self, wake: int) -> None:
        """The environment silent for ``watchdog_s`` while engaged: the force fades (counted from
        the end of this loop's own last stall: while the loop did not run, the environment's
        updates waited in the socket)."""
        proto = self.loop.proto
        if self.state == LS["engaged"] and wake - max(proto.last_update_ns, self.stall_at) > self.watchdog_ns:
            self.transition("fading", Reason.SILENT, (wake - proto.last_update_ns) * 1e-6)

    def take_tick_fade(self, now: int) -> None:
        """A tick in a thread of its own (a clock or a servo thread) started the silence fade by
        itself (``servo._locked_tick``: the target to zero, ``TK_STATE`` fading): the transition it
        stands for, before anything else of this pass (an update that arrived meanwhile then
        resumes from it; without it the loop would stay engaged with its target at zero)."""
        lp = self.loop
        if self.state == LS["engaged"] and int(lp.tk[tick.TK_STATE]) == LS["fading"]:
            self.transition("fading", Reason.SILENT, (now - lp.proto.last_update_ns) * 1e-6)

    def after_fade(self) -> None:
        """Gain reached zero while fading or stopping."""
        if self.state == LS["stopping"]:
            self.loop.proto.endpoint.close_all("server stopping")
            self.transition("stopped", Reason.STOPPED)
            return
        if self.watchdog == WD_SESSION_ENDED:
            self.transition("idle", Reason.FADED)

    # ---------------------------------------------------------------------------- faults
    def stalled_recently(self, now: int) -> bool:
        """The loop stalled long enough (and recently enough) to explain the device's watchdog.
        A stall inside this step (between its wake-up and its device write) shows only now: the
        time since the previous step's end, and it ended just now, not at the step's wake-up (the
        recovery counts its time on time from here)."""
        lp = self.loop
        t = lp.clock.now_ns()
        gap = t - int(lp.tk[tick.TK_PREV_WRITE_NS])  # one period and one step's compute when on time
        if gap > self.stall_gap_ns:
            self.stall_ns = gap
            self.stall_at = t
            self.ontime_since = t
        wd = self.dev_wd_ns if self.dev_wd_ns > 0 else 50_000_000
        return self.stall_at > 0 and now - self.stall_at <= self._stall_explains_ns and 2 * self.stall_ns >= wd

    def on_fault(self, rc: int, dev_code: int, now: int, reason: Reason | None = None) -> None:
        """A tick's fault, classified by ``lifecycle.FAULT_POLICY``."""
        lp = self.loop
        # the device's watchdog, or a remote device's link, cut by this loop's own stall
        if ((dev_code == DEV_FAULT_WATCHDOG or dev_code == DEV_FAULT_LINK) and self.state != LS["stopping"]
                and self.stalled_recently(now)):
            self.on_stall_trip(now)
            return
        if self.state == LS["fault"] or self.stopped:
            return
        if rc == ctl.RC_SPEED and not dev_code:
            if self.state == LS["idle"] and lp.ctrl.cs[ctl.CS_GAIN] <= 0.0:
                # nothing is rendered: nothing to fade, nothing that could come back by surprise;
                # a client that connects later engages as usual (lifecycle.FAULT_POLICY)
                if not self.speeding:
                    self.speeding = True
                    self.transition("idle", Reason.SPEED_IDLE)
                return
            self.fault = Fault.SPEED  # fade out (the kernel dropped the gain target), device stays on
            why = Reason.SPEED
        elif rc == ctl.RC_DIVERGED and not dev_code:
            self.fault = Fault.DIVERGED  # fade out (the kernel holds the gain target at zero), device on
            why = Reason.DIVERGED
        elif dev_code:
            self.fault = Fault.DEVICE
            self.device_fault = dev_code
            lp.device.disable()
            lp.ctrl.cut()
            why = Reason.DEVICE_FAULT
        else:
            self.fault = Fault.NONFINITE
            lp.device.disable()
            lp.ctrl.cut()
            why = Reason.NONFINITE
        self.faults_total += 1
        if self.state == LS["stopping"]:
            return  # already ramping down; the output is off
        self.transition("fault", reason or why, dev_code)

    def on_own_stall(self, now: int) -> None:
        """This loop did not run for at least the device's watchdog: a stall trip whether or not
        the device saw it. A device program that was itself not running when the stall ended
        finds the loop's new commands waiting and never trips; the output and the count of
        repeated stalls must not depend on that. A new stall while the last one's recovery
        waits counts too (the device is off then: only the loop can see it). Before anything
        is rendered, only the device's own trip matters (nothing to cut, nothing to count)."""
        st = self.state
        if st == LS["engaged"] or st == LS["fading"] or (st == LS["fault"] and self.fault == Fault.STALL):
            self.on_stall_trip(now, own=True)

    def on_stall_trip(self, now: int, own: bool = False) -> None:
        """The device's watchdog cut the output because this loop did not run in time (or the
        loop saw its own stall first). Nothing was wrong with the device or the model: once the
        loop has been on time for ``stall_recover_s`` the force ramps back in (housekeeping),
        unless it happens too often. ``own``: the loop saw the stall itself (a new one)."""
        lp = self.loop
        stall_ms = self.stall_ns * 1e-6
        if self.state == LS["fault"]:
            if self.fault == Fault.STALLS_REPEATED or (self.fault == Fault.STALL and not own):
                return  # the device's latched report of a stall already counted
        self.stall_trips += 1
        if self.state == LS["idle"] and lp.ctrl.cs[ctl.CS_GAIN] <= 0.0:
            # nothing was being rendered: no force can come back by surprise
            lp.device.enable()
            if not lp.device.fault:
                self.transition("idle", Reason.STALL_IDLE, stall_ms)
                return
        lp.device.disable()
        lp.ctrl.cut()
        self._trip_times = [t for t in self._trip_times if now - t <= self._stall_window_ns] + [now]
        self.faults_total += 1
        if len(self._trip_times) > self._stall_trips_max:
            self.fault = Fault.STALLS_REPEATED
            self.transition("fault", Reason.STALLS_REPEATED, len(self._trip_times))
        else:
            self.fault = Fault.STALL
            self.transition("fault", Reason.STALL, stall_ms)

    def _recover_from_stall(self, now: int) -> None:
        lp = self.loop
        on_time = now - self.ontime_since
        if on_time < self._recover_ns:
            return
        lp.device.enable()
        if lp.device.fault:
            lp.device.disable()
            return  # the device still refuses: try again later
        self.fault = Fault.NONE
        self.device_fault = 0
        self.stall_recoveries += 1
        self.transition("engaged" if lp.proto.session_live() else "idle", Reason.RECOVERED, on_time * 1e-9)

    def rearm(self) -> bool:
        """Clear a fault: re-enable the device; force ramps back in from zero."""
        lp = self.loop
        if self.state != LS["fault"]:
            return False
        lp.device.enable()
        if lp.device.fault:
            return False
        if self.fault == Fault.DIVERGED and lp.proto.model is not None:
            lp.proto.model.settle()  # from rest: a proxy still unstable is flagged again at once
        self.fault = Fault.NONE
        self.device_fault = 0
        self._trip_times = []
        lp.ctrl.cut()
        self.transition("engaged" if lp.proto.session_live() else "idle", Reason.REARM)
        return True

    def request_stop(self) -> None:
        """Ramp forces down, then send Bye and stop (the next steps do it)."""
        if self.stopping:
            return
        self.transition("stopping", Reason.STOP)
        if self.loop.ctrl.cs[ctl.CS_GAIN] <= 0.0:
            self.after_fade()

    def housekeeping(self, now: int) -> None:
        """What the lifecycle checks every 10 ms: a stall's recovery, a device link that came up
        before anything was rendered, a session that ended."""
        lp = self.loop
        if self.state == LS["fault"]:
            if self.fault == Fault.STALL:
                self._recover_from_stall(now)
            elif self.fault == Fault.DEVICE and self.device_fault == DEV_FAULT_LINK and not self.rendered_ever:
                # a remote device not connected yet at start-up: no force has ever been rendered,
                # so arming it when its link comes up is not a force "coming back by itself"
                lp.device.enable()
                if not lp.device.fault:
                    self.fault = Fault.NONE
                    self.device_fault = 0
                    self.transition("idle", Reason.LINK_UP)
        if self._session_ended():
            self.transition("fading", Reason.SESSION_ENDED, lp.proto.session_id)

    def _session_ended(self) -> bool:
        """The engaged session is gone (closed, timed out) and its fade not begun."""
        proto = self.loop.proto
        return bool(proto.session_id and proto.session_id not in proto.endpoint.sessions
                    and self.watchdog != WD_SESSION_ENDED and (self.state == LS["engaged"] or self.state == LS["fading"]))

    def has_housekeeping(self) -> bool:
        """:meth:`housekeeping` has something to check or do (beside a ticking thread it runs with
        the tick's lock: only then is the lock taken for it)."""
        return self.state == LS["fault"] or self._session_ended()
