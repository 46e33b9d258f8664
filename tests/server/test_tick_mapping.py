"""The workspace mapping inside the compiled haptic tick (issue 29, issue 30 section 3): the tick
maps the raw row after the read (``map_state``) and the filter's wrench before the write
(``map_command``) on the array the ``MappedDevice`` holds (``TickArrays.map``, ``TK_MAPPED``), for
a simulated device (``IO_SIM``: its plain steps run in ``tick.run_ticks`` without Python), a
driver in Python (``IO_EXTERNAL``: the loop reads and writes the driver under the mapping), a
device's C functions (``IO_NATIVE``, and a servo tick that finds the lock held) and a Touch on the
fake libHD, device-clocked. The frozen-position watch judges the raw row against the force the
device was written."""
from __future__ import annotations

import importlib.util
import os
import time

import numpy as np
import pytest
from numba import carray, cfunc, types
from server_harness import PointDevice, make_settings

from hapticproxy.server import control as ctl
from hapticproxy.server import servo, tick
from hapticproxy.server.devices import frozen as fz
from hapticproxy.server.clock import MonotonicClock
from hapticproxy.server.devices import mapping as mp
from hapticproxy.server.devices.base import DEV_FAULT_FROZEN, DEV_NSTATE, DS_BUTTONS, load_device
from hapticproxy.server.devices.mapped import MappedDevice
from hapticproxy.server.shm import LS, TEL

PLANAR = [0, 1, 5]  # what a planar device renders: fx, fy, tz


def _push_on_wall(**device):
    """A planar sim device mapped at scale 2 (offset 0.1 m in x), its hand pushing 0.5 N onto the
    testbed's wall."""
    return make_settings(device={"kind": "planar", "watchdog_s": 0.0, "workspace_scale": 2.0,
                                 "workspace_offset_m": [0.1, 0.0, 0.0],
                                 "hand": {"type": "constant", "wrench": [0.0, -0.5, 0.0], "start": "server"},
                                 **device})


def _raw_row(dev) -> np.ndarray:
    row = np.zeros(DEV_NSTATE)
    dev.inner.read(row)
    return row


def test_a_mapped_sim_device_writes_each_ticks_command_mapped_and_runs_plain_steps_compiled(rig_factory):
    """In simulated time each step's device command is the image of that step's command (scene
    force / 2, written in the tick that computed it, from the ramp-in to the wall); then, on the
    real clock, ``run_ticks`` runs 50 plain steps by itself (``TK_TICKS``) with the mapping on:
    the scene's force is 1 N, the device renders 0.5 N, the scene's position is 2 x + 0.1."""
    s = _push_on_wall()
    dev = load_device("sim", s["device"], period_s=1e-3)
    assert isinstance(dev, MappedDevice)
    r = rig_factory(settings=s, device=dev)
    loop = r.loop
    assert loop._io == tick.IO_SIM and loop.tk[tick.TK_MAPPED] == 1  # the driver's arrays, in the tick
    sent = []

    def same_tick(_i):
        sent.append(loop.ctrl.cmd[1])
        np.testing.assert_array_equal(dev.inner.last_command[PLANAR], 0.5 * loop.ctrl.cmd[PLANAR])

    r.run(2.0, on_step=same_tick)
    assert max(sent) > 0.9 and len(set(sent)) > 100  # the force ramped in (the steps differed)

    tk = loop.tk
    while tk[tick.TK_NEEDS_PYTHON]:  # what the last update left (nothing arrives from here on)
        loop.step()
    now = time.monotonic_ns()
    tk[tick.TK_RX_PENDING] = 0
    tk[tick.TK_POLL_EVERY] = 1 << 40
    tk[tick.TK_WATCHDOG_NS] = 1 << 50     # (the silent environment is test_run_ticks')
    tk[tick.TK_QUIET_SINCE_NS] = now
    tk[tick.TK_HK_COUNT] = 0
    tk[tick.TK_HK_EVERY] = 50
    tk[tick.TK_SPIN_NS] = 20_000
    tk[tick.TK_LAST_WRITE_NS] = now
    tk[tick.TK_DEADLINE_NS] = now + loop.period_ns
    n0, ret0, head0 = int(tk[tick.TK_TICKS]), int(tk[tick.TK_RETURNS]), int(loop.shared.head[0])
    assert tick.run_ticks_at(loop._desc_addr) == tick.EV_TICKED
    assert int(tk[tick.TK_TICKS]) - n0 == 50 and int(tk[tick.TK_RETURNS]) - ret0 == 1 and tk[tick.TK_RC] == 0
    head = int(loop.shared.head[0])
    assert head - head0 == 50
    rows = loop.shared.ring[np.arange(head0, head) % loop.shared.ring_rows]
    assert np.all(rows[:, TEL["loop_state"]] == LS["engaged"])
    assert abs(np.mean(rows[:, TEL["cmd_fy"]]) - 1.0) < 0.02                          # the scene's force
    np.testing.assert_array_equal(dev.inner.last_command[PLANAR], 0.5 * loop.ctrl.cmd[PLANAR])  # the hand's
    assert abs(dev.inner.last_command[1] - 0.5) < 0.01
    raw = _raw_row(dev)  # (one device step after the row the last tick read: the handle is at rest)
    np.testing.assert_allclose(loop.dev[0:2], 2.0 * raw[0:2] + (0.1, 0.0), atol=1e-6)
    assert abs(raw[0] - loop.dev[0]) > 0.05  # (the offset and the scale show)


def test_the_clutch_in_the_tick_fades_holds_and_ramps_in_within_the_rate_limit(rig_factory):
    """The hand holds the handle pressed on the wall, holds the clutch from 2 s to 3 s and lifts the
    handle 10 mm meanwhile. The device's force fades out over the ramp (0.4 s: longer than the
    frozen-position window, 0.2 s, while the scene's row is held still on purpose), nothing is
    rendered once faded, and it ramps back in after the release: no step of the device's force
    exceeds what the safety filter's rate limit lets through (1 N per step of the scene's, 0.5 N
    at this hand; the press zeroes the scene's twist, a step of some 0.06 N), none after the
    release more than a ramp's step; the watch, judging the raw row, never trips."""
    hand = {"type": "impedance", "start": "server",
            "target": {"type": "waypoints", "points": [[0.0, [0, 0, 0]], [1.0, [0, -0.02, 0]], [2.5, [0, -0.02, 0]],
                                                       [2.7, [0, -0.01, 0]], [5.0, [0, -0.01, 0]]]},
            "buttons": [[0.0, 0], [2.0, 1], [3.0, 0]]}
    s = make_settings(device={"kind": "planar", "watchdog_s": 0.0, "workspace_scale": 2.0, "clutch_button": 0,
                              "clutch_ramp_s": 0.4, "hand": hand},
                      safety={"frozen_s": 0.2, "frozen_force_n": 0.05})
    dev = load_device("sim", s["device"], period_s=1e-3)
    r = rig_factory(settings=s, device=dev)
    assert r.loop.ctrl.cp[ctl.CP_FROZEN + fz.FP_WINDOW_NS] == 0.2e9  # the tick's watch is on, mapped or not
    felt = []
    r.run(5.0, on_step=lambda i: felt.append(dev.inner.last_command[1]))
    felt = np.array(felt)
    rows = np.array(r.rows)
    t = rows[:, TEL["t_s"]] - rows[0, TEL["t_s"]]
    rate = float(r.loop.shared.get("rate_limit_n_per_step"))
    assert rate == pytest.approx(1.0)
    assert r.loop.faults_total == 0 and np.all(rows[t > 1.0, TEL["loop_state"]] == LS["engaged"])
    assert np.all(felt[(t > 1.8) & (t < 2.0)] > 0.2)                        # pressed on the wall
    assert np.all(felt[(t > 2.41) & (t < 3.0)] == 0.0)                      # clutched: nothing rendered
    assert np.all(np.abs(np.diff(felt)) <= rate / 2.0)                       # never beyond the rate limit
    assert np.all(felt[(t > 2.0) & (t < 2.3)] > 0.02)                     # faded over the ramp, not cut
    back = np.abs(np.diff(felt))[(t[1:] >= 3.0) & (t[1:] < 3.4)]
    assert back.size and back.max() < 0.01                                  # ramps back in, no kick
    assert abs(felt[-1]) > 0.02
    np.testing.assert_allclose(rows[t > 4.5, TEL["dev_y"]], rows[t > 4.5, TEL["proxy_y"]], atol=1e-4)
    assert dev.clutch_gain == 1.0 and dev.mapping[mp.M_CLUTCHES] == 1 and not dev.clutched


class _ButtonPoint(PointDevice):
    """The harness's point device (a driver in Python, no frozen-position watch of its own) with a
    clutch button and a position that can freeze; it keeps the raw row it last reported."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.buttons = 0.0
        self.frozen = None
        self.last_row = np.zeros(DEV_NSTATE)

    def read(self, s):
        rc = super().read(s)
        s[DS_BUTTONS] = self.buttons
        if self.frozen is not None:
            s[0:3] = self.frozen
            s[7:10] = 0.0
        self.last_row[:] = s[:DEV_NSTATE]
        return rc


def test_a_mapped_driver_in_python_is_mapped_in_the_tick_and_watched_on_its_raw_row(rig_factory):
    """A driver in Python behind a mapping: the loop reads and writes the driver itself, the tick
    maps (the row 2 x + 0.1, the rendered force half the scene's, each step). Its raw position
    frozen while the clutch holds (the device written nothing) is no fault, though the scene's
    command holds the wall's force; frozen once the force is back, it trips the watch."""
    s = make_settings(device={"kind": "planar", "watchdog_s": 0.0}, safety={"frozen_s": 0.2, "frozen_force_n": 0.05})
    inner = _ButtonPoint(hand=lambda t: (0.0, -0.5, 0.0), period_s=1e-3)
    dev = MappedDevice(inner, mp.new_mapping(scale=2.0, offset_m=(0.1, 0.0, 0.0), clutch_button=0, ramp_steps=50))
    r = rig_factory(settings=s, device=dev)
    loop = r.loop
    assert loop._io == tick.IO_EXTERNAL and loop.tk[tick.TK_MAPPED] == 1

    def mapped(_i):
        np.testing.assert_array_equal(loop.dev[0:2], 2.0 * inner.last_row[0:2] + (0.1, 0.0))
        np.testing.assert_array_equal(inner.commands[-1][:2], 0.5 * loop.ctrl.cmd[:2])
        assert inner.commands[-1][2] == loop.ctrl.cmd[5]

    r.run(1.5, on_step=mapped)
    assert loop.state_name == "engaged" and abs(loop.ctrl.cmd[1] - 1.0) < 0.05
    inner.buttons = 1.0
    r.run(0.1)
    assert dev.clutched and not np.any(np.array(inner.commands[-40:]))
    inner.frozen = inner.last_row[0:3].copy()
    scene = []
    r.run(0.5, on_step=lambda i: scene.append(loop.ctrl.cmd[1]))  # 2.5 windows: frozen, nothing pushes
    assert loop.state_name == "engaged" and loop.device_fault == 0
    assert min(scene) > 0.1 and not np.any(np.array(inner.commands[-400:]))  # (the scene's command is no push)
    inner.buttons = 0.0                         # the force comes back onto a frozen sensor
    r.run(0.4)
    assert loop.device_fault == DEV_FAULT_FROZEN and loop.faults_total == 1


_SIG = types.int32(types.CPointer(types.float64), types.CPointer(types.float64))
_NBUF = 40
_W = 30  # the buffer's slots 30..35: the wrench last written; 0..22: the row reported


@cfunc(_SIG)
def _native_read(ctx, row):
    src = carray(ctx, (_NBUF,))
    dst = carray(row, (DEV_NSTATE,))
    for i in range(DEV_NSTATE):
        dst[i] = src[i]
    return 0


@cfunc(_SIG)
def _native_write(ctx, w):
    buf = carray(ctx, (_NBUF,))
    src = carray(w, (6,))
    for i in range(6):
        buf[_W + i] = src[i]
    return 0


def test_a_native_device_is_written_the_mapped_command_and_a_held_servo_tick_writes_it_again(rig_factory):
    """``IO_NATIVE`` (a device's C functions: here two cfuncs over a buffer): the tick maps the row
    its read returns and writes the mapped command; a servo tick that finds the lock held writes
    that same device-frame command again, not the scene's."""
    s = _push_on_wall(workspace_rotation=[0.0, 0.0, 0.3])
    dev = load_device("sim", s["device"], period_s=1e-3)
    r = rig_factory(settings=s, device=dev)
    r.run(1.5)
    loop = r.loop
    assert loop.state_name == "engaged" and abs(loop.ctrl.cmd[1]) > 0.5
    buf = np.zeros(_NBUF)
    buf[:DEV_NSTATE] = _raw_row(dev)
    tk, m = loop.tk, dev.mapping
    tk[tick.TK_IO] = tick.IO_NATIVE
    tk[tick.TK_NATIVE_READ] = _native_read.address
    tk[tick.TK_NATIVE_WRITE] = _native_write.address
    tk[tick.TK_NATIVE_CTX] = buf.ctypes.data
    want_row = buf[:DEV_NSTATE].copy()
    mp.map_state(want_row, m.copy())
    wake = int(tk[tick.TK_DEADLINE_NS])
    assert tick.tick_at(loop._desc_addr, wake, 0) == 0
    np.testing.assert_array_equal(loop.dev, want_row)                          # mapped after the read
    want = np.zeros(6)
    mp.map_command(loop.ctrl.cmd, m.copy(), want)                              # (the gain stays 1)
    np.testing.assert_array_equal(buf[_W:_W + 6], want)                        # mapped before the write
    assert np.abs(want[:2] - loop.ctrl.cmd[:2]).max() > 0.1

    b = servo.ServoBinding(loop.period_ns)
    b.bind(loop._T)
    buf[_W:_W + 6] = np.nan
    tk[tick.TK_LOCK] = 2                                                      # Python holds the tick
    servo.servo_tick(b.block)
    assert b.block[servo.SB_HELD] == 1 and b.block[servo.SB_TICKS] == 0
    np.testing.assert_array_equal(buf[_W:_W + 6], want)                        # the device's, again
    tk[tick.TK_LOCK] = 0
    servo.servo_tick(b.block)
    assert b.block[servo.SB_TICKS] == 1
    np.testing.assert_array_equal(buf[_W:_W + 6], m[mp.M_CMD:mp.M_CMD + 6])


@pytest.mark.skipif(importlib.util.find_spec("pyOpenHaptics") is None, reason="pyopenhaptics is not installed")
def test_a_mapped_touch_runs_device_clocked_with_its_mapping(tmp_path):
    """A Touch on the fake libHD (its own 1 kHz servo thread, its physics in its own process) with
    a mapping (scale 2, 0.1 m up): the servo thread runs the compiled tick, the mapping applied
    (the handle rests at z = 50 mm: the scene has it at 0.2 m). Counts and positions only."""
    from hapticproxy.server import config as cfgmod
    from hapticproxy.server.loop import HapticLoop
    from hapticproxy.testing.emulators.block import Block
    from hapticproxy.testing.emulators.harness import attach_hd_devices
    from hapticproxy.testing.emulators.physics import spawn

    blk = Block(str(tmp_path / "dev.blk"), create=True)
    procs = [spawn(blk.path, "Touch", vendor="touch", initial_pose=[0.0, 0.0, 0.05, 0.0, 0.0, 0.0])]
    loop = None
    try:
        attach_hd_devices({"Default Device": blk.path}, lockstep=False)
        settings = cfgmod.load({"loop": {"rate_hz": 1000.0, "realtime": False},
                                "transport": {"url": f"mem://tick-mapping-touch-{os.getpid()}"},
                                "device": {"driver": "touch", "kind": "spatial", "watchdog_s": 0.5, "stale_s": 0.5,
                                           "workspace_scale": 2.0, "workspace_offset_m": [0.0, 0.0, 0.1]},
                                "telemetry": {"ring_s": 1.0},
                                "controller": {"stiffness_n_per_m": 300.0, "damping_n_s_per_m": 2.0}})
        loop = HapticLoop.build(settings, clock=MonotonicClock())
        assert isinstance(loop.device, MappedDevice) and loop.device_clocked
        loop.warm_up()
        loop.start()
        head0 = int(loop.shared.head[0])
        loop.run(duration_s=0.5)
        ran = int(loop.servo.block[servo.SB_TICKS])
        assert ran > 50 and loop.tk[tick.TK_IO] == tick.IO_NATIVE and loop.tk[tick.TK_MAPPED] == 1
        assert loop.faults_total == 0, loop.counters()
        raw_z = float(blk.view("pos_m")[2])
        assert raw_z == pytest.approx(0.05, abs=1e-4)
        assert loop.dev[2] == pytest.approx(2.0 * raw_z + 0.1, abs=1e-4)       # the scene's
        head = int(loop.shared.head[0])
        rows = loop.shared.ring[np.arange(max(head0, head - 100), head) % loop.shared.ring_rows]
        assert len(rows) > 50
    finally:
        if loop is not None:
            loop.close()
        blk["stop"] = 1.0
        for p in procs:
            try:
                p.wait(timeout=10)
            except Exception:  # noqa: BLE001
                p.kill()
        blk.close()


class _PythonMapped:
    """The mapping as the loop ran it before the tick did: a driver in Python whose ``read`` and
    ``write`` are the ``MappedDevice``'s (the kernels called from Python around the sim driver's
    own read and write). Opaque to the loop (no ``mapping``, a no-op ``watch_frozen``: that loop
    ran no watch behind a mapping)."""

    def __init__(self, mapped: MappedDevice) -> None:
        self.m = mapped
        self.kind, self.name = mapped.kind, mapped.name

    limits = property(lambda self: self.m.limits)
    info = property(lambda self: self.m.info)
    enabled = property(lambda self: self.m.enabled)
    fault = property(lambda self: self.m.fault)

    def __getattr__(self, name):
        if name in ("enable", "disable", "read", "write", "on_engage", "close"):
            return getattr(self.m, name)
        raise AttributeError(name)

    def watch_frozen(self, frozen_s, min_force_n):
        pass


def test_the_compiled_mapping_renders_what_the_python_wrapper_rendered_bit_for_bit(rig_factory):
    """The clutch scenario (scale 2, turned 0.3 rad, offset; press at 2 s, release at 2.5 s) twice:
    the sim device mapped in the tick (``IO_SIM``), and the same device mapped in Python around
    its driver's read and write (``IO_EXTERNAL``, as before the tick mapped): every rendered
    wrench, every telemetry row's device, command and proxy columns and the mapping's state end
    identical."""
    hand = {"type": "impedance", "start": "server",
            "target": {"type": "waypoints", "points": [[0.0, [0, 0, 0]], [1.0, [0, -0.02, 0]], [2.0, [0, -0.02, 0]],
                                                       [2.2, [0, -0.01, 0]], [4.0, [0, -0.01, 0]]]},
            "buttons": [[0.0, 0], [2.0, 1], [2.5, 0]]}
    cols = [TEL[k] for k in TEL if k.startswith(("dev_", "cmd_", "proxy_"))]
    runs = []
    for python in (False, True):
        s = make_settings(device={"kind": "planar", "watchdog_s": 0.0, "workspace_scale": 2.0, "clutch_button": 0,
                                  "clutch_ramp_s": 0.1, "workspace_rotation": [0.0, 0.0, 0.3],
                                  "workspace_offset_m": [0.05, -0.02, 0.0], "hand": hand})
        dev = load_device("sim", s["device"], period_s=1e-3)
        r = rig_factory(settings=s, device=_PythonMapped(dev) if python else dev)
        assert (r.loop._io, int(r.loop.tk[tick.TK_MAPPED])) == ((tick.IO_EXTERNAL, 0) if python else (tick.IO_SIM, 1))
        felt = []
        r.run(4.0, on_step=lambda i: felt.append(dev.inner.last_command))
        m = dev.mapping.copy()
        m[mp.M_CMD:mp.M_CMD + 6] = 0.0  # (the tick's output block; the wrapper has its own)
        runs.append((np.array(felt), np.array(r.rows)[:, cols], m, r.loop.faults_total))
    (fa, ra, ma, na), (fb, rb, mb, nb) = runs
    assert na == nb == 0 and ma[mp.M_CLUTCHES] == 1 and np.count_nonzero(fa[:, 1]) > 3000
    np.testing.assert_array_equal(fa, fb)
    np.testing.assert_array_equal(ra, rb)
    np.testing.assert_array_equal(ma, mb)
