"""The update slot (``server/model/slot.py``): Python stages a decoded update, the tick applies it
with the model's own kernel and leaves what acknowledges it; the handshake is two words
(``TK_UPD_SEQ``, ``TK_UPD_DONE``), so an update needs no lock beside a ticking thread. Simulated
time: each test runs the tick itself (``tick.tick_at``) where the clock thread would."""
from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from server_harness import receive_update, tick_once

from hapticproxy.server import control as ctl
from hapticproxy.server import tick
from hapticproxy.server.devices.base import DS_BUTTONS
from hapticproxy.server.lifecycle import LS
from hapticproxy.server.model.layout import K_M, K_UPDATES
from hapticproxy.server.model.slot import AX_HAND, AX_INPUTS, NAX, descriptor, new_slot, slot_at


@njit(cache=False)
def _write_through(addr):
    U = slot_at(addr)
    U.keys[1, 2] = 7
    U.pos[2, 1] = 0.5
    U.sep[3] = -0.25
    U.q[1] = 3.0
    U.newI[0, 1] = 9
    U.lw_e[0, 0] = 2.0
    U.ack_lw[0, 1] = 4.0
    U.ax[NAX - 1] = 1.5
    return U.nrm.shape[0] + U.newF.shape[0]


def test_the_slots_descriptor_gives_views_of_its_own_arrays():
    U = new_slot(5, 8, 3, 0)
    d = descriptor(U)
    assert _write_through(int(d.__array_interface__["data"][0])) == 5 + 8
    assert U.keys[1, 2] == 7 and U.pos[2, 1] == 0.5 and U.sep[3] == -0.25 and U.q[1] == 3.0
    assert U.newI[0, 1] == 9 and U.lw_e[0, 0] == 2.0 and U.ack_lw[0, 1] == 4.0 and U.ax[NAX - 1] == 1.5


def _received(r):
    """The engaged rig's loop, protocol side, tick words and model, and the update just received
    (pending, not staged) with the time it was received."""
    lp = r.loop
    upd = receive_update(r)
    return lp, lp.proto, lp.tk, lp.proto.model, upd, r.clock.now_ns()


@pytest.fixture
def engaged(rig_factory):
    r = rig_factory(env_kwargs={"start_pose": (0.0, 0.011, 0.0)})  # the tool by the wall: contacts
    r.run(0.5)
    assert r.loop.state_name == "engaged"
    return r


def test_the_tick_applies_a_staged_update_and_leaves_its_acknowledgement(engaged):
    """Staged: nothing changes in the model until a tick; that tick applies it (the model's own
    update count, the tick's ``TK_UPDATES``), steps with it, and leaves its state in the slot (the
    acknowledgement's: the state after that tick's step, not before it), the hand wrench and the
    device's inputs of that tick; then the slot is Python's (``TK_UPD_DONE``)."""
    r = engaged
    lp, proto, tk, m, upd, now = _received(r)
    n_upd = int(m._cnt[K_UPDATES])
    ticks_updates = int(tk[tick.TK_UPDATES])
    proto.exchange(now)
    assert proto._staged is upd and int(m._cnt[K_UPDATES]) == n_upd  # not applied by staging
    assert int(tk[tick.TK_UPD_SEQ]) != int(tk[tick.TK_UPD_DONE])
    U = m.slot
    U.ack_st[:] = np.nan
    tick_once(lp, now)
    assert int(tk[tick.TK_UPD_SEQ]) == int(tk[tick.TK_UPD_DONE]) and int(tk[tick.TK_UPD_CODE]) == 0
    assert int(m._cnt[K_UPDATES]) == n_upd + 1 and int(tk[tick.TK_UPDATES]) == ticks_updates + 1
    assert int(m._cnt[K_M]) == upd.keys.shape[0] >= 1
    np.testing.assert_array_equal(U.ack_st, m._st)  # after the tick's step
    np.testing.assert_array_equal(U.ax[AX_HAND:AX_HAND + 6], lp.ctrl.cs[ctl.CS_HAND:ctl.CS_HAND + 6])
    np.testing.assert_array_equal(U.ax[AX_INPUTS:AX_INPUTS + 3], lp.dev[DS_BUTTONS:DS_BUTTONS + 3])
    acks = proto.acks
    tick_once(lp, now + lp.period_ns)  # a tick with nothing staged leaves the slot alone
    assert not np.array_equal(U.ack_st, m._st)
    proto.exchange(now + lp.period_ns)
    assert proto.acks == acks + 1 and proto._staged is None


def test_an_update_the_models_kernel_refuses_changes_nothing_and_is_not_acknowledged(engaged):
    """The codec checks what it can; the model's kernel has the last word (here a normal broken in
    the slot after staging): refused, the model keeps its contacts, counted as an update error,
    no acknowledgement, the updates not counted, the silence not reset."""
    r = engaged
    lp, proto, tk, m, upd, now = _received(r)
    proto.exchange(now)
    assert proto._staged is upd and upd.keys.shape[0] >= 1
    m.slot.nrm[0] = (0.0, 0.0, 0.0)
    C = m._C.copy()
    quiet = int(tk[tick.TK_QUIET_SINCE_NS])
    errors, acks, updates = proto.update_errors, proto.acks, int(tk[tick.TK_UPDATES])
    tick_once(lp, now)
    assert int(tk[tick.TK_UPD_CODE]) != 0 and int(tk[tick.TK_UPD_DONE]) == int(tk[tick.TK_UPD_SEQ])
    assert int(tk[tick.TK_UPDATES]) == updates and int(tk[tick.TK_QUIET_SINCE_NS]) == quiet
    proto.exchange(now)
    assert proto.update_errors == errors + 1 and proto.acks == acks and proto._staged is None
    np.testing.assert_array_equal(m._C[:, :3], C[:, :3])


def test_a_staged_update_is_not_silence(engaged):
    """The environment's watchdog passed but an update waits in the slot: not silent (the tick
    applies it next); once the tick is done with the slot, silent."""
    r = engaged
    lp, proto, tk, _, upd, now = _received(r)
    proto.exchange(now)
    assert proto._staged is upd
    late = int(tk[tick.TK_QUIET_SINCE_NS]) + int(tk[tick.TK_WATCHDOG_NS]) + 1
    assert int(tk[tick.TK_STATE]) == LS["engaged"]
    assert not tick.silent(tk, late)
    tk[tick.TK_UPD_DONE] = tk[tick.TK_UPD_SEQ]
    assert tick.silent(tk, late)


def test_a_model_dropped_with_an_update_staged_leaves_nothing_for_the_tick(engaged):
    """The session ends (the model goes) while an update waits in the slot: the slot is forgotten
    (``TK_UPD_DONE`` = ``TK_UPD_SEQ``, no slot address), and the next ticks apply nothing."""
    r = engaged
    lp, proto, tk, _, upd, now = _received(r)
    proto.exchange(now)
    assert proto._staged is upd
    proto.drop_model()
    assert int(tk[tick.TK_UPD_DESC]) == 0 and int(tk[tick.TK_UPD_DONE]) == int(tk[tick.TK_UPD_SEQ])
    assert proto._staged is None
    updates = int(tk[tick.TK_UPDATES])
    tick_once(lp, r.clock.now_ns())
    assert int(tk[tick.TK_UPDATES]) == updates


def test_a_silence_that_passes_while_an_update_is_staged_is_not_a_fade(engaged):
    """The single-thread step: the environment's watchdog passes in the step whose tick applies
    the update staged in the step before: no fade (it was heard), no transition at all."""
    r = engaged
    lp, proto = r.loop, r.loop.proto
    upd = receive_update(r)
    proto.exchange(r.clock.now_ns())
    assert proto._staged is upd
    n = len(lp.shared.transitions_since(0))
    # the update before it, heard longer ago than the watchdog by the next step's wake-up
    heard = proto._staged_ns
    assert lp.life.stall_at < heard
    proto.last_update_ns = int(lp.tk[tick.TK_QUIET_SINCE_NS]) - lp.life.watchdog_ns
    lp.tk[tick.TK_QUIET_SINCE_NS] = proto.last_update_ns
    lp.step()
    assert proto._staged is None and lp.state_name == "engaged" and proto.last_update_ns == heard
    assert len(lp.shared.transitions_since(0)) == n


def test_the_compiled_loop_hands_back_the_tick_that_applied_an_update(engaged):
    """``run_ticks`` (the single-thread compiled loop) returns right after the tick that applied a
    staged update (``EV_TICKED``): its acknowledgement is Python's, not left for the next
    datagram or housekeeping. Real deadlines for a few periods, nothing else due."""
    import time

    r = engaged
    lp, proto, tk, _, upd, now = _received(r)
    proto.exchange(now)
    assert proto._staged is upd
    now = time.monotonic_ns()  # (run_ticks waits on CLOCK_MONOTONIC)
    tk[tick.TK_DEADLINE_NS] = now + lp.period_ns
    tk[tick.TK_LAST_WRITE_NS] = now
    tk[tick.TK_QUIET_SINCE_NS] = now
    tk[tick.TK_UPD_HEARD_NS] = now
    tk[tick.TK_FD] = -1
    tk[tick.TK_POLL_EVERY] = 1 << 40
    tk[tick.TK_POLL_COUNT] = 0
    tk[tick.TK_RX_PENDING] = 0
    tk[tick.TK_NEEDS_PYTHON] = 0
    tk[tick.TK_HK_COUNT] = 0
    tk[tick.TK_HK_EVERY] = 4  # (a bound: housekeeping hands back after 4 ticks anyway)
    tk[tick.TK_STALL_GAP_NS] = 1 << 40  # (a loaded machine's late wake-up is no stall here)
    tk[tick.TK_SIMULATED] = 0
    ticks = int(tk[tick.TK_TICKS])
    assert tick.run_ticks_at(lp._desc_addr) == tick.EV_TICKED
    assert int(tk[tick.TK_TICKS]) == ticks + 1 and int(tk[tick.TK_UPD_DONE]) == int(tk[tick.TK_UPD_SEQ])


def test_the_tick_reads_no_slot_without_a_model(rig_factory):
    """No model engaged (no slot address): a sequence word out of step (a bug elsewhere, a stale
    word) makes the tick apply nothing and read nothing, rather than read a slot at address 0."""
    r = rig_factory()
    lp = r.loop
    tk = lp.tk
    assert lp.proto.model is None and int(tk[tick.TK_UPD_DESC]) == 0
    tk[tick.TK_UPD_SEQ] = int(tk[tick.TK_UPD_DONE]) + 1
    updates = int(tk[tick.TK_UPDATES])
    tick_once(lp, r.clock.now_ns())
    assert int(tk[tick.TK_UPDATES]) == updates and int(tk[tick.TK_UPD_DONE]) != int(tk[tick.TK_UPD_SEQ])


def test_a_linkages_acknowledgement_is_the_state_of_the_tick_that_applied_it():
    """A 3-bar chain pushed onto a floor: the tick that applies a staged update leaves the model's
    state and the links' poses of that tick in the slot (the joint state the ProxyState reports is
    computed from them), and the hand wrench of that tick, component by component."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_linkage_loop import LinkageRig

    r = LinkageRig()
    try:
        r.run(1.0)
        lp, proto = r.loop, r.loop.proto
        assert lp.state_name == "engaged" and proto._linkage
        m = proto.model
        receive_update(r)
        now = r.clock.now_ns()
        proto.exchange(now)
        assert proto._staged is not None
        U = m.slot
        U.ack_lw[:] = np.nan
        U.ax[:] = np.nan
        tick_once(lp, now)
        np.testing.assert_array_equal(U.ack_lw, m._lw)
        np.testing.assert_array_equal(U.ack_st, m._st)
        hand = lp.ctrl.cs[ctl.CS_HAND:ctl.CS_HAND + 6]
        assert len(set(hand.tolist())) > 1  # (the push: components that differ)
        np.testing.assert_array_equal(U.ax[AX_HAND:AX_HAND + 6], hand)
        acks = proto.acks
        proto.exchange(now)
        assert proto.acks == acks + 1
    finally:
        r.close()
