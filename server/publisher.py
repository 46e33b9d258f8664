"""The loop's status publisher: the one owner of what the loop writes to the shared status block.

``StatusPublisher.publish(now)`` copies the loop's counters, its state and its parts' figures (the
lifecycle's faults and stalls, the protocol side's sessions and updates, the controller's safety
counters, the compiled loop's and the servo thread's ticks, the energy ledger) into
``SharedState.status``, from which the supervisor answers ``status`` and the live views read. It
runs in housekeeping (every 10 ms) and at the end of a run, never per step.
"""
from __future__ import annotations

from . import control as ctl
from . import passivity as pv
from . import tick
from .shm import ST

#: status slots that show one of the endpoint's counters as it is: (slot, counter attribute)
_ENDPOINT_STATUS = tuple((ST[slot], attr) for slot, attr in (
    ("decode_errors", "decode_errors"), ("sessions_opened", "sessions_opened"),
    ("datagrams_received", "received"), ("bad_token", "bad_token"), ("wrong_peer", "wrong_peer"),
    ("unknown_session", "unknown_session"), ("bad_mac", "bad_mac"), ("unexpected", "unexpected"),
    ("rejects_sent", "rejects_sent"), ("refused_out_of_bounds", "out_of_bounds"),
    ("refused_unusable", "unusable"), ("refused_seq_jump", "seq_jump")))


class StatusPublisher:
    """Writes one ``HapticLoop``'s figures to its shared status block (its ``publisher``)."""

    def __init__(self, loop) -> None:
        self.loop = loop

    def publish(self, now: int) -> None:
        lp = self.loop
        life, proto = lp.life, lp.proto
        st = lp.shared.status
        ec = proto.endpoint.counters
        tc = proto.transport.counters
        cc = lp.ctrl.cc
        st[ST["t_last_ns"]] = now
        st[ST["updates"]] = proto.updates
        st[ST["acks_sent"]] = proto.acks
        st[ST["stale_or_duplicate"]] = ec.stale + ec.duplicate
        for i, attr in _ENDPOINT_STATUS:
            st[i] = getattr(ec, attr)
        st[ST["dropped_packets"]] = ec.dropped + getattr(tc, "dropped_oversize_recv", 0)
        st[ST["contacts"]] = proto.contacts()
        st[ST["session_id"]] = proto.session_id
        st[ST["loop_state"]] = life.state
        st[ST["watchdog"]] = life.watchdog
        st[ST["gain"]] = lp.ctrl.cs[ctl.CS_GAIN]
        st[ST["fault"]] = life.fault
        st[ST["device_fault"]] = life.device_fault
        m = proto.model
        if m is not None:
            mc = m.counters()
            st[ST["model_nonfinite"]] = mc["nonfinite"]
            st[ST["flips_refused"]] = mc["flips_refused"]
            st[ST["rekeyed"]] = mc["rekeyed"]
            st[ST["flips_taken"]] = mc["flips_taken"]
            st[ST["diverged"]] = mc["diverged"]
            st[ST["recovering"]] = mc["recovering"]
            st[ST["held"]] = mc["held"]
            st[ST["recovery_energy_j"]] = m.recovery_energy_j
        else:
            st[ST["model_nonfinite"]] = 0
            st[ST["recovering"]] = 0
            st[ST["held"]] = 0
        if proto.advice is not None:
            st[ST["advised_epsilon_m"]] = proto.advice.epsilon_m
            st[ST["advised_lead_s"]] = proto.advice.lead_s
        st[ST["saturated"]] = cc[ctl.CC_SATURATED]
        st[ST["rate_limited"]] = cc[ctl.CC_RATE_LIMITED]
        st[ST["speed_trips"]] = cc[ctl.CC_SPEED_TRIPS]
        st[ST["env_silence_ms"]] = (now - proto.last_update_ns) * 1e-6 if proto.last_update_ns else -1.0
        st[ST["env_rate_hz"]] = proto.env_rate_hz
        st[ST["engagements"]] = proto.engagements
        st[ST["faults_total"]] = life.faults_total
        st[ST["telemetry_overwritten"]] = max(0, int(lp.shared.head[0]) - lp.shared.ring_rows)
        st[ST["wrong_version"]] = proto.endpoint.codec.counters.unknown_major
        st[ST["dropped_empty"]] = getattr(tc, "dropped_empty", 0)
        st[ST["poll_budget_cuts"]] = proto.poll_cut
        st[ST["stall_trips"]] = life.stall_trips
        st[ST["stall_recoveries"]] = life.stall_recoveries
        st[ST["torque_cap_n_m"]] = lp.ctrl.torque_cap_n_m
        st[ST["ticks_compiled"]] = lp.tk[tick.TK_TICKS]
        st[ST["energy_hand_j"]] = lp.ctrl.cs[ctl.CS_EHAND]
        st[ST["tank_j"]] = lp.ctrl.tank_j
        st[ST["tank_low_j"]] = lp.ctrl.cs[ctl.CS_TANK + pv.TS_LOW]
        st[ST["passivity_limited"]] = cc[ctl.CC_TANK + pv.TC_LIMITED]
        servo = lp.servo
        if servo is not None:
            from .servo import SB_HELD, SB_TICKS

            st[ST["servo_ticks"]] = servo.block[SB_TICKS]
            st[ST["servo_held"]] = servo.block[SB_HELD]
