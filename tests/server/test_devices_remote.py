"""The remote device over real UDP on loopback: state and commands flow, newest-wins and
counted drops, the device-side watchdog and the epoch rules, link loss, and the CLI."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from server_harness import stop_process

from hapticproxy.protocol import devlink as dl
from hapticproxy.protocol.devlink import COMMAND, STATE
from hapticproxy.server.devices import base
from hapticproxy.server.devices.base import (
    DEV_FAULT_DISABLED, DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_FAULT_WATCHDOG, DEV_OK, load_device,
)
from hapticproxy.server.devices import remote
from hapticproxy.server.devices.remote import COMMAND_SIZE, STATE_V1_SIZE, DeviceProgram, RemoteDevice
from hapticproxy.server.devices.sim import make_sim_device
from hapticproxy.testing.cleanup import made_then_ended

DT = 1e-3
EXE = str(Path(sys.executable).parent / "hapticproxy")
F1 = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])


class FakeClock:
    def __init__(self) -> None:
        self.ns = 5_000_000_000

    def __call__(self) -> int:
        return self.ns

    def advance(self, s: float) -> None:
        self.ns += int(round(s * 1e9))


def eventually(cond, timeout_s=5.0):
    """Loopback delivery is immediate in practice; this only guards against a slow scheduler."""
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.001)
    return True


class Link:
    def __init__(self, kind="planar", **srv_cfg):
        self.clock = FakeClock()
        cfg = {"driver": "remote", "kind": kind, "listen": "127.0.0.1:0", **srv_cfg}
        self.srv = load_device("remote", cfg, period_s=DT, clock_ns=self.clock)
        self.sim = make_sim_device({"kind": kind, "workspace_min_m": [-5, -5, -5][: 2 if kind == "planar" else 3],
                                    "workspace_max_m": [5, 5, 5][: 2 if kind == "planar" else 3]},
                                   period_s=DT, clock_ns=self.clock)
        self.prog = DeviceProgram(self.sim, self.srv.local_address, watchdog_s=0.05, clock_ns=self.clock)
        self.row = np.zeros(base.DEV_NSTATE)

    def step(self, n=1, wrench=F1, *, server=True):
        """n periods: the device ticks, then (if ``server``) the server reads and writes."""
        st = None
        for _ in range(n):
            self.clock.advance(DT)
            self.prog.tick()
            if server:
                self.srv.read(self.row)
                st = self.srv.write(wrench)
        return st

    def engage(self, n):
        """Two periods for the link to come up, enable, then ``n`` periods writing F1."""
        self.step(2)
        self.srv.enable()
        self.step(n)

    def close(self):
        self.prog.close()
        self.srv.close()


@pytest.fixture
def link():
    yield from made_then_ended(Link)


def test_state_flows_and_the_link_fault_clears_only_through_enable(link):
    lk = link()
    assert lk.srv.read(lk.row) == DEV_FAULT_LINK and not lk.srv.link_up   # nothing heard yet
    lk.step(3, server=False)
    assert eventually(lambda: lk.srv.read(lk.row) is not None and lk.srv.counters()["states"] >= 3)
    assert lk.srv.link_up and lk.srv.fault == DEV_FAULT_LINK                # latched until enable
    assert lk.row == pytest.approx(lk.sim.state, nan_ok=True)  # (no inputs: NaN both sides)
    assert lk.srv.device_session == lk.prog.session
    lk.srv.enable()
    assert lk.srv.fault == DEV_OK and lk.srv.enabled


def test_commands_flow_and_move_the_device(link):
    lk = link()
    lk.engage(300)
    assert lk.prog.armed and lk.srv.device_armed
    assert lk.sim.last_command.tolist() == F1.tolist()
    assert lk.row[7] > 0.0 and lk.row[0] > 0.0                 # the state coming back moved
    c = lk.srv.counters()
    assert c["commands_sent"] >= 300 and c["malformed"] == 0 and c["stale"] == 0
    assert lk.prog.counters()["arms"] == 1


def test_server_keeps_the_newest_state_and_counts_what_it_drops():
    clock = FakeClock()
    srv = RemoteDevice(kind="planar", limits=base.DeviceLimits(10, 0.5, 2, 20), listen=("127.0.0.1", 0),
                       clock_ns=clock, link_timeout_s=0.1)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))
    try:
        def state(seq, x, *, session=100, kind=1, sock=tx, magic=None, nan=False):
            row = base.empty_state()
            row[0] = x
            if nan:
                row[8] = np.nan
            buf = bytearray(STATE.pack(flags=0, device_session=session, server_session=0, epoch=0, period_us=1000,
                                       seq=seq, cmd_seq=0, kind=kind, fault=0, state=row))
            if magic:
                buf[:4] = magic
            sock.sendto(bytes(buf), srv.local_address)

        row = np.zeros(base.DEV_NSTATE)
        state(10, 0.01)
        state(5, 0.02)                       # older
        state(10, 0.03)                      # the same again
        state(11, 0.04, magic=b"XXXX")
        tx.sendto(b"\x00" * 10, srv.local_address)
        state(12, 0.05, nan=True)            # non-finite twist
        state(13, 0.06, sock=other)          # another address, same session
        state(14, 0.07, session=99)          # an older boot of the device
        assert eventually(lambda: (srv.read(row), sum(srv.counters().values()))[1] >= 8)
        c = srv.counters()
        assert row[0] == 0.01
        assert (c["states"], c["stale"], c["duplicate"], c["malformed"], c["foreign"], c["old_session"]) == \
            (1, 1, 1, 3, 1, 1)
        state(11, 0.08)                      # newer: kept
        state(12, 0.09, kind=2)              # the wrong kind: a hardware fault, state not taken
        assert eventually(lambda: (srv.read(row), srv.counters()["kind_mismatch"])[1] == 1)
        assert row[0] == 0.08 and srv.fault == DEV_FAULT_HARDWARE
        srv.enable()
        assert srv.fault == DEV_FAULT_HARDWARE           # the cause is still there
        state(1, 0.10, session=200)          # the device restarted (newer boot epoch)
        assert eventually(lambda: (srv.read(row), srv.counters()["device_restarts"])[1] == 1)
        assert row[0] == 0.10 and srv.device_session == 200
        srv.enable()
        assert srv.fault == DEV_OK
        clock.advance(0.2)                   # that device fell silent; one with an older epoch
        state(1, 0.11, session=150)          # (its host's clock went back) is a restart too
        assert eventually(lambda: (srv.read(row), srv.counters()["device_restarts"])[1] == 2)
        assert row[0] == 0.11 and srv.device_session == 150 and srv.fault == DEV_FAULT_LINK
    finally:
        tx.close()
        other.close()
        srv.close()


def test_a_device_fault_latches_only_under_the_full_server_session():
    """A STATE reporting a fault under this driver's key latches it; under a server session that
    differs only in its high half (another server's key) it does not, and neither is a device
    session that differs only in its high half taken for the current device."""
    clock = FakeClock()
    srv = RemoteDevice(kind="planar", limits=base.DeviceLimits(10, 0.5, 2, 20), listen=("127.0.0.1", 0),
                       clock_ns=clock, link_timeout_s=0.1)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    row = np.zeros(base.DEV_NSTATE)
    dev = 0x0000_0123_4567_89AB
    try:
        def state(seq, *, server_session, fault=DEV_OK, session=dev):
            tx.sendto(STATE.pack(flags=1, device_session=session, server_session=server_session, epoch=srv.epoch,
                                 period_us=1000, seq=seq, cmd_seq=0, kind=1, fault=fault, state=base.empty_state()),
                      srv.local_address)

        state(1, server_session=0)
        assert eventually(lambda: (srv.read(row), srv.counters()["states"])[1] == 1)
        srv.enable()
        assert srv.fault == DEV_OK and srv.session >> 32 != 0
        state(2, server_session=srv.session ^ (1 << 40), fault=DEV_FAULT_WATCHDOG)
        assert eventually(lambda: (srv.read(row), srv.counters()["states"])[1] == 2)
        assert srv.fault == DEV_OK and srv.counters()["device_faults"] == 0
        state(1, server_session=srv.session, session=dev ^ (1 << 44))  # another boot: a restart, not this one
        assert eventually(lambda: (srv.read(row), srv.counters()["device_restarts"])[1] == 1)
        assert srv.device_session == dev ^ (1 << 44)
        srv.enable()
        state(2, server_session=srv.session, session=dev ^ (1 << 44), fault=DEV_FAULT_WATCHDOG)
        assert eventually(lambda: (srv.read(row), srv.counters()["device_faults"])[1] == 1)
        assert srv.fault == DEV_FAULT_WATCHDOG
    finally:
        tx.close()
        srv.close()


def test_a_pinned_device_address_is_the_only_one_heard():
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    pinned = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    pinned.bind(("127.0.0.1", 0))
    host, port = pinned.getsockname()
    srv = load_device("remote", {"kind": "1dof", "listen": "127.0.0.1:0", "device_address": f"{host}:{port}"},
                      period_s=DT, clock_ns=FakeClock())
    try:
        for seq, sock in ((1, tx), (2, pinned)):
            r = base.empty_state()
            r[0] = seq
            sock.sendto(STATE.pack(flags=0, device_session=7, server_session=0, epoch=0, period_us=1000, seq=seq,
                                   cmd_seq=0, kind=0, fault=0, state=r), srv.local_address)
        row = np.zeros(base.DEV_NSTATE)
        assert eventually(lambda: (srv.read(row), srv.counters()["states"])[1] == 1)
        assert srv.counters()["foreign"] == 1 and row[0] == 2.0 and srv.device_address == (host, port)
        srv.enable()
        srv.write(F1)                          # the command goes to the pinned address
        pinned.settimeout(5.0)
        data = pinned.recv(4096)
        c = COMMAND.unpack(data)
        assert len(data) == COMMAND_SIZE and c.flags & 1 and c.device_session == 7 and c.epoch == srv.epoch
    finally:
        srv.close()
        tx.close()
        pinned.close()
    with pytest.raises(ValueError, match="device.device_address: cannot resolve"):
        load_device("remote", {"listen": "127.0.0.1:0", "device_address": "no-such-host.invalid:5"}, period_s=DT)


def test_device_watchdog_zeroes_latches_and_only_a_new_enable_rearms(link):
    lk = link()
    lk.engage(20)
    assert lk.prog.armed and lk.sim.enabled
    lk.step(60, server=False)                 # the server loop stalls for 60 ms > 50 ms
    assert not lk.prog.armed and lk.prog.fault == DEV_FAULT_WATCHDOG and not lk.sim.enabled
    assert np.all(lk.sim.last_command == 0.0)
    lk.step(30)                               # the server resumes with the same epoch
    assert not lk.prog.armed and np.all(lk.sim.last_command == 0.0)
    # the server latched the device's report and now sends zero with the enable flag clear
    assert lk.srv.fault == DEV_FAULT_WATCHDOG and lk.srv.counters()["device_faults"] == 1
    assert lk.prog.counters()["disarms"] == 1
    lk.srv.enable()                           # a new epoch re-arms it
    lk.step(5)
    assert lk.prog.armed and lk.prog.fault == DEV_OK and lk.sim.last_command[0] == 1.0
    assert lk.srv.fault == DEV_OK and lk.prog.counters()["watchdog_trips"] == 1


def test_device_epoch_rules_with_crafted_commands():
    clock = FakeClock()
    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    sim = make_sim_device({"kind": "1dof"}, period_s=DT, clock_ns=clock)
    prog = DeviceProgram(sim, server.getsockname(), watchdog_s=0.05, clock_ns=clock)
    def cmd(seq, *, session=1000, epoch=1, enable=True, f=1.0, device=None):
        server.sendto(COMMAND.pack(flags=int(enable), device_session=prog.session if device is None else device,
                                   server_session=session, epoch=epoch, engagements=0, seq=seq, state_seq=0,
                                   wrench=[f, 0, 0, 0, 0, 0]), prog.local_address)

    def tick(n=1):
        for _ in range(n):
            clock.advance(DT)
            prog.tick()

    try:
        tick()
        cmd(1, device=prog.session + 1)        # addressed to another boot of the device
        tick()
        assert not prog.armed and prog.counters()["foreign_session"] == 1
        cmd(1, device=prog.session ^ (1 << 40))  # ... one differing only in the high half
        cmd(1, device=prog.session ^ (1 << 62))
        tick()
        assert not prog.armed and prog.counters()["foreign_session"] == 3
        cmd(1)
        tick()
        assert prog.armed and sim.last_command[0] == 1.0
        cmd(3, f=0.5)
        cmd(2, f=0.7)                          # reordered: older than 3
        cmd(3, f=0.9)                          # duplicate
        server.sendto(b"junk", prog.local_address)
        tick()
        c = prog.counters()
        assert sim.last_command[0] == 0.5 and (c["stale"], c["duplicate"], c["malformed"]) == (1, 1, 1)
        tick(60)                               # no command for 60 ms
        assert prog.fault == DEV_FAULT_WATCHDOG and not prog.armed
        cmd(4)                                 # same key: cannot re-arm
        cmd(1, session=999, epoch=7)           # an older server session (before a restart)
        tick()
        assert not prog.armed and prog.counters()["old_key"] == 1 and prog.counters()["ignored_latched"] == 1
        cmd(1, epoch=2)                        # the server's next enable()
        tick()
        assert prog.armed and prog.fault == DEV_OK and sim.last_command[0] == 1.0
        cmd(2, epoch=2, enable=False)          # disable: zero at once, not a fault
        tick()
        assert not prog.armed and prog.fault == DEV_OK and np.all(sim.last_command == 0.0)
        cmd(1, session=2000, epoch=1)          # a restarted server (newer session) arms
        tick()
        assert prog.armed and prog.key == (2000, 1)
        cmd(2, session=2000, epoch=1, f=float("nan"))
        tick()
        assert not prog.armed and prog.counters()["nonfinite_refused"] == 1
        # the state stream reports key, fault and armed flag
        server.setblocking(False)
        data = b""
        while True:
            try:
                data = server.recv(4096)
            except BlockingIOError:
                break
        st = dl.STATE_V1.unpack(data)  # (a device without inputs sends layout version 1)
        assert len(data) == STATE_V1_SIZE and st.device_session == prog.session and (st.server_session, st.epoch) == (2000, 1)
        assert st.flags & 1 == 0 and st.fault == base.DEV_FAULT_NONFINITE_COMMAND
    finally:
        prog.close()
        server.close()


def test_link_loss_latches_until_enable_and_zeroes_the_device(link):
    lk = link(link_timeout_s=0.1)
    lk.engage(10)
    assert lk.prog.armed
    lk.clock.advance(0.15)                    # no state for 150 ms
    assert lk.srv.read(lk.row) == DEV_FAULT_LINK and not lk.srv.link_up
    assert lk.srv.counters()["link_losses"] == 1
    lk.step(20)                               # the device comes back; the server keeps writing F1
    assert lk.srv.link_up and lk.srv.fault == DEV_FAULT_LINK
    assert not lk.prog.armed and np.all(lk.sim.last_command == 0.0)   # told to zero, stays zero
    lk.srv.enable()
    lk.step(3)
    assert lk.srv.fault == DEV_OK and lk.prog.armed


def test_disable_zeroes_the_device_at_once(link):
    lk = link()
    lk.engage(10)
    assert lk.prog.armed
    lk.srv.disable()
    lk.step(1, server=False)
    assert not lk.prog.armed and np.all(lk.sim.last_command == 0.0)
    assert lk.step(5) == DEV_FAULT_DISABLED and not lk.prog.armed


def test_remote_config_validation():
    for cfg, key in (({"kind": "hexapod"}, "device.kind"), ({"listen": "nowhere"}, "device.listen"),
                     ({"link_timeout_s": 0}, "device.link_timeout_s"), ({"colour": 1}, "device.colour"),
                     ({"device_address": "1.2.3.4"}, "device.device_address"),
                     ({"kind": "1dof", "max_torque_n_m": 1.0}, "device.max_torque_n_m")):
        with pytest.raises(ValueError) as exc:
            load_device("remote", cfg, period_s=DT)
        assert str(exc.value).startswith(key + ":"), exc.value
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    try:
        with pytest.raises(ValueError, match="device.listen: cannot bind"):
            load_device("remote", {"listen": "127.0.0.1:%d" % busy.getsockname()[1]}, period_s=DT)
    finally:
        busy.close()
    dev = load_device("remote", {"kind": "spatial", "listen": "127.0.0.1:0", "max_force_n": 3.0}, period_s=DT)
    try:
        assert isinstance(dev, RemoteDevice) and dev.kind == "spatial" and dev.limits.max_force_n == 3.0
        assert dev.limits.watchdog_s == 0.05
    finally:
        dev.close()


@pytest.mark.parametrize("argv", [
    ["--kind", "hexapod", "--server", "127.0.0.1:9"],
    ["--kind", "planar"],
    ["--server", "nohost"],
    ["--server", "127.0.0.1:9", "--rate", "-5"],
    ["--server", "127.0.0.1:9", "--rate", "fast"],
    ["--server", "127.0.0.1:9", "--hand", "{bad json"],
    ["--server", "127.0.0.1:9", "--hand", "wave"],
    ["--server", "127.0.0.1:9", "--config", "/nonexistent/dev.toml"],
    ["--server", "127.0.0.1:9", "--bogus"],
])
def test_device_cli_bad_arguments_one_line_exit_2(argv, capsys):
    assert remote.main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("hapticproxy device: error:"), err
    assert "Traceback" not in err


def test_device_cli_bad_arguments_through_the_installed_command():
    out = subprocess.run([EXE, "device", "--kind", "hexapod", "--server", "127.0.0.1:9"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and "hexapod" in out.stderr


def test_device_program_process_streams_and_obeys(tmp_path):
    """``hapticproxy device`` in its own process, paced in real time, against the server driver."""
    srv = load_device("remote", {"kind": "1dof", "listen": "127.0.0.1:0", "link_timeout_s": 1.0}, period_s=DT)
    port = srv.local_address[1]
    proc = subprocess.Popen([EXE, "device", "--kind", "1dof", "--server", f"127.0.0.1:{port}", "--rate", "500",
                             "--watchdog-s", "0.5", "--duration", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert srv.wait_for_link(60.0), "no state from the device process"
        row = np.zeros(base.DEV_NSTATE)
        srv.enable()
        assert srv.fault == DEV_OK
        assert eventually(lambda: (srv.read(row), srv.write(F1), srv.device_armed and row[7] > 0.01)[2],
                          timeout_s=30.0)
        assert row[0] > 0.0
        srv.disable()
        assert eventually(lambda: (srv.read(row), not srv._dev_armed)[1], timeout_s=30.0)
    finally:
        err = stop_process(proc)
        srv.close()
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "states_sent" in err


def test_device_cli_runs_from_a_server_config_file(tmp_path, capsys):
    """The server's own TOML (driver = "remote", its link keys) configures the device program."""
    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    port = server.getsockname()[1]
    cfg = tmp_path / "scene.toml"
    cfg.write_text('[device]\ndriver = "remote"\nkind = "spatial"\nlisten = "127.0.0.1:%d"\n'
                   'link_timeout_s = 0.2\nmax_force_n = 4.0\n\n[device.hand]\ntype = "constant"\n'
                   'wrench = [0.1, 0, 0, 0, 0, 0]\nstart = "server"\n' % port)  # no server engages here
    try:
        rc = remote.main(["--config", str(cfg), "--server", f"127.0.0.1:{port}", "--rate", "200",
                          "--duration", "0.1"])
        assert rc == 0
        server.setblocking(False)
        got = []
        while True:
            try:
                got.append(server.recv(4096))
            except BlockingIOError:
                break
        assert got and all(len(d) == STATE_V1_SIZE for d in got)  # (no inputs: layout version 1)
        st = dl.STATE_V1.unpack(got[-1])
        assert st.kind == 2                                  # spatial
        row = st.state
        assert row[13] == 0.1 and row[0] > 0.0               # the hand pushed it
        err = capsys.readouterr().err
        assert "spatial sim device" in err and "Traceback" not in err
    finally:
        server.close()


def test_a_bound_device_program_hears_only_its_server():
    """``--bind``: the program's socket is bound, not connected; datagrams from anyone but the
    server are dropped as foreign (the kernel no longer filters them)."""
    clock = FakeClock()
    srv = RemoteDevice(kind="planar", limits=base.DeviceLimits(10, 0.5, 2, 20), listen=("127.0.0.1", 0),
                       clock_ns=clock)
    sim = make_sim_device({"kind": "planar"}, period_s=DT, clock_ns=clock)
    prog = DeviceProgram(sim, srv.local_address, bind=("127.0.0.1", 0), watchdog_s=0.05, clock_ns=clock)
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    row = np.zeros(base.DEV_NSTATE)
    try:
        for _ in range(3):
            clock.advance(DT)
            prog.tick()
            assert eventually(lambda: (srv.read(row), srv.link_up)[1])
        srv.enable()
        srv.write(F1)
        c = COMMAND.unpack(COMMAND.pack(flags=1, device_session=prog.session, server_session=srv.session + 1, epoch=9,
                                        engagements=0, seq=1, state_seq=0, wrench=[5.0, 0, 0, 0, 0, 0]))
        other.sendto(COMMAND.pack(**c._asdict()), prog.local_address)   # a newer key, from a stranger
        assert eventually(lambda: (prog.tick(), prog.counters()["foreign"] + prog.counters()["arms"])[1] >= 2)
        assert prog.counters()["foreign"] == 1 and prog.key == (srv.session, srv.epoch) and prog.armed
    finally:
        other.close()
        prog.close()
        srv.close()


def test_both_ends_run_over_any_transport_in_lock_step():
    """The link on ``mem://`` (no sockets): the same rules, deterministic."""
    from hapticproxy.protocol.transport import MemTransport

    clock = FakeClock()
    s_tr, c_tr = MemTransport.pair()
    srv = RemoteDevice(kind="1dof", limits=base.DeviceLimits(10, 0.0, 2, float("inf")), transport=s_tr,
                       clock_ns=clock)
    sim = make_sim_device({"kind": "1dof"}, period_s=DT, clock_ns=clock)
    prog = DeviceProgram(sim, transport=c_tr, watchdog_s=0.05, clock_ns=clock)
    row = np.zeros(base.DEV_NSTATE)
    try:
        clock.advance(DT)
        prog.tick()
        srv.read(row)
        assert srv.link_up and srv.device_address == c_tr.client_id
        srv.enable()
        for _ in range(5):
            clock.advance(DT)
            prog.tick()
            srv.read(row)
            srv.write(F1)
        assert prog.armed and sim.last_command[0] == 1.0 and srv.device_armed
        assert srv.counters()["commands_sent"] == 5 and prog.counters()["commands"] == 4
        a, b = MemTransport.pair()
        try:
            with pytest.raises(ValueError, match="server-role"):
                RemoteDevice(kind="1dof", limits=srv.limits, transport=b)
        finally:
            b.close()
            a.close()
    finally:
        prog.close()
        srv.close()


# ---------------------------------------------------------------- any driver (issue 32, papercut 3)
@pytest.mark.parametrize("config, argv, want", [
    (None, [], "sim"),                                                      # no config: the simulated device
    ('driver = "remote"\nkind = "spatial"', [], "sim"),                     # the server's own file
    ('driver = "haply"\nport = "/dev/ttyACM0"', [], "haply"),               # a device-side file
    ('driver = "haply"', ["--driver", "sim"], "sim"),                       # --driver wins
    (None, ["--driver", "touch", "--kind", "spatial"], "touch"),
])
def test_device_cli_bridges_the_driver_asked_for(tmp_path, monkeypatch, config, argv, want):
    """``--driver NAME``, else the config's ``device.driver`` unless it is ``remote``, else sim;
    built by ``base.load_device`` from the ``[device]`` table less the remote link's keys."""
    built = {}

    def fake_load(name, cfg, *, period_s, clock_ns=None):
        built.update(name=name, cfg=dict(cfg), period_s=period_s)
        return make_sim_device({"kind": cfg.get("kind", "planar")}, period_s=period_s)

    monkeypatch.setattr(base, "load_device", fake_load)
    args = ["--server", "127.0.0.1:9", "--rate", "250", *argv]
    if config is not None:
        (tmp_path / "d.toml").write_text(f'[device]\n{config}\nlisten = "127.0.0.1:9"\nlink_timeout_s = 0.2\n')
        args += ["--config", str(tmp_path / "d.toml")]
    prog, driver = remote._device_from_args(remote._build_parser().parse_args(args))
    prog.close()
    assert driver == built["name"] == built["cfg"]["driver"] == want
    assert not {"listen", "link_timeout_s", "device_address", "connect_timeout_s"} & set(built["cfg"])
    assert built["period_s"] == pytest.approx(1 / 250)


@pytest.mark.parametrize("argv, says", [
    (["--driver", "touch", "--hand", "constant"], "--hand: only the simulated device"),
    (["--driver", "remote"], "--driver: remote is the server's end"),
    (["--driver", "nosuch"], "device.driver"),
])
def test_device_cli_refuses_a_driver_it_cannot_bridge_in_one_line(argv, says, capsys):
    assert remote.main(["--server", "127.0.0.1:9", *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"hapticproxy device: error: {says}"), err


def test_device_cli_bridges_a_vendor_driver_over_its_emulator(tmp_path):
    """``hapticproxy device`` with the Force Dimension driver on the unmodified forcedimension-core
    over the fake libdrd, whose physics runs in its own process in real time: the server's remote
    driver sees the device's state, arms it, and the push it sends moves the handle and is what
    the emulated motors render; a disarm zeroes them."""
    import importlib.util

    if importlib.util.find_spec("forcedimension_core") is None:
        pytest.skip("forcedimension-core is not installed (the devices extra)")
    from hapticproxy.testing.emulators.block import Block
    from hapticproxy.testing.emulators.harness import sdk_root
    from hapticproxy.testing.emulators.physics import spawn

    block = Block(tmp_path / "dev.blk", create=True)
    physics = spawn(block.path, 33, vendor="forcedimension", serial=4242)  # an omega.3
    srv = load_device("remote", {"kind": "spatial", "listen": "127.0.0.1:0", "link_timeout_s": 1.0}, period_s=DT)
    cfg = tmp_path / "device.toml"
    # the firmware watchdog off: a stall of this shared machine's scheduler is not under test here
    cfg.write_text('[device]\ndriver = "forcedimension"\nwatchdog_s = 0.0\n')
    env = dict(os.environ, FDSDK=str(sdk_root()), HAPTICPROXY_EMU_BLOCKS=block.path)
    proc = subprocess.Popen([EXE, "device", "--config", str(cfg), "--server", f"127.0.0.1:{srv.local_address[1]}",
                             "--rate", "500", "--watchdog-s", "0.5", "--duration", "120"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        t_end = time.monotonic() + 120.0
        while not srv.wait_for_link(0.2):
            assert proc.poll() is None, f"the device program exited: {proc.communicate()[1]}"
            assert time.monotonic() < t_end, "no state from the device program"
        row = np.zeros(base.DEV_NSTATE)
        srv.read(row)
        x0 = row[0]
        srv.enable()
        assert eventually(lambda: (srv.read(row), srv.write(F1), srv.device_armed and row[0] > x0 + 0.002)[2],
                          timeout_s=60.0)
        assert block.view("rendered")[0] == pytest.approx(1.0)
        srv.disable()
        assert eventually(lambda: (srv.read(row), not srv._dev_armed and block.view("rendered")[0] == 0.0)[1],
                          timeout_s=30.0)
    finally:
        err = stop_process(proc)
        srv.close()
        block["stop"] = 1.0
        try:
            physics.wait(10)
        except subprocess.TimeoutExpired:
            physics.kill()
            physics.wait()
        block.close()
    assert proc.returncode == 0, err
    assert "spatial forcedimension device -> 127.0.0.1" in err and "Force Dimension omega.3 #4242" in err, err
    assert "Traceback" not in err and "states_sent" in err
