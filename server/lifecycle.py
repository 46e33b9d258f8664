"""The haptic loop's lifecycle: its states, the transitions between them, why each happens.

One table (:data:`TRANSITIONS`) says which state may follow which; the loop changes state only
through ``HapticLoop.transition(to, reason)``, which checks the table, applies what the new state
means for the force and the proxy (:data:`RENDERS`), counts the transition and writes it to the
shared transition log, from which the supervisor logs every one of them with its reason.

States (what the device gets, what the proxy does):

- ``starting``: kernels loading; nothing is written.
- ``idle``: no session drives the model; zero force; no proxy.
- ``engaged``: a session drives the model; the force ramps in (``ramp_in_s``) and is then
  rendered in full; the device drives the proxy. While the force ramps in, the device is
  re-indexed onto the proxy every step, so a hand that keeps pushing stores nothing in the
  coupling (see ``control._slide``).
- ``fading``: the environment is silent past ``safety.watchdog_s`` or its session ended: the force
  fades to zero over ``fade_s``; the proxy is held (a device that renders less and less must not
  push it into what it touches).
- ``fault``: output off (device disabled, or faded for a speed trip); the proxy is held. A fault
  caused by a late loop (a stall of the loop process at least as long as the device's watchdog:
  the device's trip, or the loop's own when the device did not see it, as a device program that
  was itself late does not) recovers by itself once the loop has been on time for
  ``safety.stall_recover_s``; more than ``safety.stall_trips_max`` such trips within
  ``safety.stall_window_s`` latch (a new stall while one's recovery waits counts). Every other
  fault (a non-finite value, a fault the device reports, a speed trip) waits for a re-arm.
- ``stopping``: ramping down before exit; ``stopped``: done.
"""
from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

from ..protocol.devlink import DeviceFault
from ..protocol.messages import ServerState

LOOP_STATES = ("idle", "engaged", "fading", "fault", "stopping", "stopped", "starting")
#: state name -> code (float: it is stored in the float64 status block and telemetry rows)
LS = {name: float(i) for i, name in enumerate(LOOP_STATES)}

#: Which states may follow which. A state may follow itself only where an event is worth logging
#: without a change of state (a stall while idle, a session ending while already fading).
TRANSITIONS: dict[str, frozenset[str]] = {
    "starting": frozenset({"idle", "fault", "stopping"}),
    "idle": frozenset({"idle", "engaged", "fault", "stopping"}),
    "engaged": frozenset({"fading", "fault", "stopping"}),
    "fading": frozenset({"fading", "engaged", "idle", "fault", "stopping"}),
    "fault": frozenset({"engaged", "idle", "fault", "stopping"}),
    "stopping": frozenset({"stopped", "stopping"}),
    "stopped": frozenset(),
}

#: What each state tells an engine (``ProxyState.server_state``).
SERVER_STATE = {
    "starting": ServerState.IDLE, "idle": ServerState.IDLE, "engaged": ServerState.ENGAGED,
    "fading": ServerState.FADING, "stopping": ServerState.FADING, "stopped": ServerState.IDLE,
    "fault": ServerState.FAULT,
}
#: ServerState by loop-state code, for the acknowledgement path (no dict of names per ack).
SERVER_STATE_BY_CODE = tuple(int(SERVER_STATE[name]) for name in LOOP_STATES)


class Fault(IntEnum):
    """Why the loop is in ``fault`` (``status`` shows the name)."""

    NONE = 0
    NONFINITE = 1       # a non-finite value before the device: zero wrench, device disabled
    DEVICE = 2          # the device reported a fault: device disabled
    SPEED = 3           # the device moved faster than its limit: forces faded, device on
    STALL = 4           # the device's watchdog tripped because the loop was late: recovers by itself
    STALLS_REPEATED = 5  # more stall trips than allowed in the window: latched
    DIVERGED = 6        # the model's integration diverged: forces faded, device on


FAULT_TEXT = {
    Fault.NONE: "none",
    Fault.NONFINITE: "non-finite value before the device (zero wrench, device disabled)",
    Fault.DEVICE: "device fault (device disabled)",
    Fault.SPEED: "device speed over its limit (forces faded)",
    Fault.STALL: "device watchdog tripped by a late loop (recovers once the loop is on time)",
    Fault.STALLS_REPEATED: "device watchdog tripped by late loops too often (latched)",
    Fault.DIVERGED: "the proxy's integration diverged (forces faded)",
}
#: Faults that clear by themselves; every other one waits for ``status --rearm``.
SELF_CLEARING = frozenset({Fault.STALL})

#: A device watchdog or link fault is explained by the loop's own stall (not the device's fault)
#: when the stall ended at most this long before the fault is seen: a device reports a trip at
#: its next exchange, a remote one within its link's latency. Later, it is the device's own.
STALL_EXPLAINS_S = 1.0



class Reason(IntEnum):
    """Why a transition happened (logged by the supervisor with the transition's detail value)."""

    START = 1
    ENGAGE = 2            # detail: session id
    SILENT = 3            # detail: ms since the last ContactUpdate
    RESUMED = 4           # the environment spoke again while fading
    SESSION_ENDED = 5     # detail: session id
    FADED = 6             # the fade reached zero
    NONFINITE = 7
    DEVICE_FAULT = 8      # detail: the device's fault code
    SPEED = 9
    STALL = 10            # detail: the stall, ms
    STALL_IDLE = 11       # detail: the stall, ms (nothing was rendered: re-enabled at once)
    STALLS_REPEATED = 12  # detail: trips within the window
    RECOVERED = 13        # detail: s on time before recovering
    REARM = 14
    LINK_UP = 15          # a remote device's link came up before anything was rendered
    STOP = 16
    STOPPED = 17
    UPDATE_ERROR = 18     # an update raised: treated as a non-finite value
    SPEED_IDLE = 19       # the handle moved faster than its limit while nothing was rendered
    DIVERGED = 20         # the model flagged its integration as diverged


REASON_TEXT = {
    Reason.START: "loop started",
    Reason.ENGAGE: "session {detail:.0f} engaged: force ramps in",
    Reason.SILENT: "environment silent for {detail:.0f} ms: force fades",
    Reason.RESUMED: "environment back: force ramps in",
    Reason.SESSION_ENDED: "session {detail:.0f} ended: force fades",
    Reason.FADED: "force faded to zero",
    Reason.NONFINITE: "non-finite value before the device: zero wrench, device disabled; re-arm with `hapticproxy status --rearm`",
    Reason.DEVICE_FAULT: "device fault {detail:.0f}: device disabled; re-arm with `hapticproxy status --rearm`",
    Reason.SPEED: "device faster than its limit: forces faded; re-arm with `hapticproxy status --rearm`",
    Reason.STALL: "the loop stalled {detail:.0f} ms and the device's watchdog cut the output; recovers once on time",
    Reason.STALL_IDLE: "the loop stalled {detail:.0f} ms before anything was rendered; device re-enabled",
    Reason.STALLS_REPEATED: "{detail:.0f} stall trips within safety.stall_window_s: latched; re-arm with "
                            "`hapticproxy status --rearm`",
    Reason.RECOVERED: "loop on time for {detail:.2f} s after a stall: force ramps in",
    Reason.REARM: "re-armed",
    Reason.LINK_UP: "device link up",
    Reason.STOP: "stop requested: force ramps down",
    Reason.STOPPED: "stopped",
    Reason.UPDATE_ERROR: "a contact update could not be applied: zero wrench, device disabled; re-arm with "
                         "`hapticproxy status --rearm`",
    Reason.SPEED_IDLE: "the handle moved faster than its limit while nothing was rendered (counted; nothing "
                       "to fade)",
    Reason.DIVERGED: "the proxy's integration diverged (a velocity flipping every step without decaying): forces "
                     "faded; re-arm with `hapticproxy status --rearm`",
}


#: The device fault's own words where the generic advice is wrong for it: a remote device's
#: link that is down before anything was rendered comes back by itself (``LINK_UP``).
DEVICE_FAULT_TEXT = {
    int(DeviceFault.FROZEN): "device fault 6 (position frozen: the device's position stayed bit-identical for "
       "safety.frozen_s while force was commanded: a stuck sensor or a hung firmware, or the handle held against its "
       "mechanical stop): device disabled; move the handle, then re-arm with `hapticproxy status --rearm`",
    int(DeviceFault.LINK): "device fault 4 (link: no state from the remote device within its link timeout): output off; "
       "clears by itself when the device program connects before a session engaged (`hapticproxy device "
       "...`), else re-arm with `hapticproxy status --rearm`",
}


def describe(reason: int, detail: float) -> str:
    try:
        why = Reason(int(reason))
        if why == Reason.DEVICE_FAULT:
            code = int(detail) if detail == detail else -1
            if code in DEVICE_FAULT_TEXT:
                return DEVICE_FAULT_TEXT[code]
            name = _device_fault_name(code)
            if name:
                return f"device fault {code} ({name}): device disabled; re-arm with `hapticproxy status --rearm`"
        return REASON_TEXT[why].format(detail=detail)
    except (ValueError, KeyError):
        return f"reason {int(reason)}"


class Policy(NamedTuple):
    """What the loop does about one source of trouble (a row of :data:`FAULT_POLICY`)."""

    key: str
    source: str
    output: str      # "cut": zero at once, device disabled; "fade": to zero over fade_s, device on;
                     # "none": nothing is rendered, nothing to do
    recovery: str    # how force comes back
    fault: Fault     # the loop's fault code while it lasts (NONE: not a fault state)
    reason: Reason   # the transition's reason


#: Every source of trouble and its policy, one row each (``tests/server/test_fault_policy.py``
#: runs each row; ``docs/architecture.md`` shows the table). The loop classifies in
#: ``HapticLoop._on_fault`` / ``_on_own_stall`` / the silence and session checks.
FAULT_POLICY: tuple[Policy, ...] = (
    Policy("stall_explained", "device watchdog, explained by the loop's own stall (it ended at most STALL_EXPLAINS_S before)",
           "cut", f"by itself once the loop has been on time for safety.stall_recover_s; more than "
           f"safety.stall_trips_max trips within safety.stall_window_s latch", Fault.STALL, Reason.STALL),
    Policy("own_stall_engaged", "the loop's own stall of at least the device's watchdog while force is rendered (seen or not by "
           "the device)", "cut", "as the row above", Fault.STALL, Reason.STALL),
    Policy("own_stall_idle", "the loop's own stall while nothing is rendered", "none", "nothing to recover: logged",
           Fault.NONE, Reason.STALL_IDLE),
    Policy("watchdog_unexplained", "device watchdog not explained by a stall (e.g. 5 s after a recovered one)", "cut", "re-arm",
           Fault.DEVICE, Reason.DEVICE_FAULT),
    Policy("hardware", "device hardware fault, or a device that disabled itself", "cut", "re-arm", Fault.DEVICE,
           Reason.DEVICE_FAULT),
    Policy("frozen", "the device's position bit-identical for safety.frozen_s while at least safety.frozen_force_n was "
           "commanded (a stuck sensor, a hung firmware: devices.frozen)", "cut", "re-arm", Fault.DEVICE,
           Reason.DEVICE_FAULT),
    Policy("link_lost", "device link lost (remote device) after force was ever rendered, not explained by a stall", "cut",
           "re-arm", Fault.DEVICE, Reason.DEVICE_FAULT),
    Policy("link_not_up", "device link not yet up at start-up (nothing ever rendered)", "none", "by itself when the link "
           "comes up", Fault.DEVICE, Reason.LINK_UP),
    Policy("nonfinite", "non-finite device state, command or model result", "cut", "re-arm", Fault.NONFINITE, Reason.NONFINITE),
    Policy("update_error", "a contact update that raised while applied", "cut", "re-arm", Fault.NONFINITE, Reason.UPDATE_ERROR),
    Policy("speed_engaged", "device faster than its limit while force is rendered", "fade", "re-arm", Fault.SPEED, Reason.SPEED),
    Policy("speed_idle", "device faster than its limit while nothing is rendered", "none", "nothing to recover: counted and "
           "logged", Fault.NONE, Reason.SPEED_IDLE),
    Policy("diverged", "the model's integration diverged (a velocity flipping every step without decaying for "
           "model.layout.DIVERGE_STEPS steps; the force held at zero while it lasts)", "fade", "re-arm", Fault.DIVERGED,
           Reason.DIVERGED),
    Policy("env_silent", "environment silent for safety.watchdog_s", "fade", "by itself when updates resume (the force "
           "ramps in)", Fault.NONE, Reason.SILENT),
    Policy("session_ended", "the session ended (Bye, timeout)", "fade", "a new session engages (ramps in)", Fault.NONE,
           Reason.SESSION_ENDED),
)


def _device_fault_name(code: int) -> str:
    try:
        return DeviceFault(code).name.lower().replace("_", " ")
    except ValueError:
        return ""


def policy_table() -> str:
    """:data:`FAULT_POLICY` as the markdown table ``docs/architecture.md`` shows (a test keeps the
    two the same)."""
    lines = ["| source | output | recovery | fault | reason |", "| --- | --- | --- | --- | --- |"]
    for p in FAULT_POLICY:
        lines.append(f"| {p.source} | {p.output} | {p.recovery} | {p.fault.name.lower()} | "
                     f"{p.reason.name.lower()} |")
    return "\n".join(lines)
