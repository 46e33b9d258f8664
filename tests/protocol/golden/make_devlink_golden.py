"""Write ``devlink_golden.json``: the remote-device link's datagrams as the hand-written
``struct`` packers of ``server/devices/remote.py`` made them before the link was declared once
(``protocol/devlink.py``). Run once from the old code (commit 76e3fb7); the file is the
reference the declared layout must reproduce (``tests/protocol/test_devlink.py``).

    python tests/protocol/golden/make_devlink_golden.py   # rewrites devlink_golden.json here

Two parts: ``fields`` (one datagram per entry from explicit field values, edge values included)
and ``session`` (the datagrams a device program and a server driver actually exchanged over
loopback in a fixed, simulated-time script: ``dir``, hex).
"""
from __future__ import annotations

import json
import math
import socket
from pathlib import Path

import numpy as np

from hapticproxy.server.devices import remote as R
from hapticproxy.server.devices.base import DEV_NSTATE, empty_state
from hapticproxy.server.devices.sim import make_sim_device

OUT = Path(__file__).with_name("devlink_golden.json")
U64 = (1 << 64) - 1
U32 = (1 << 32) - 1


def _state_fields():
    row = empty_state()
    row[:7] = [0.01, -0.02, 0.0, math.cos(0.1), 0.0, 0.0, math.sin(0.1)]
    row[7:13] = [0.1, -0.2, 0.0, 0.0, 0.0, 1.5]
    row[19] = 12.345
    full = np.arange(DEV_NSTATE, dtype=float) * 0.5 - 3.0
    odd = full.copy()
    odd[13:19] = [math.nan, math.inf, -math.inf, -0.0, 1e-300, 1e300]
    return [
        dict(device_session=1, server_session=0, epoch=0, period_us=1000, seq=1, cmd_seq=0, kind=1, fault=0,
             armed=False, state=row.tolist()),
        dict(device_session=1_700_000_000_123_456_789, server_session=1_700_000_001_000_000_000, epoch=7,
             period_us=250, seq=123456, cmd_seq=123000, kind=2, fault=2, armed=True, state=full.tolist()),
        dict(device_session=U64, server_session=U64, epoch=U32, period_us=U32, seq=U64, cmd_seq=U64, kind=255,
             fault=255, armed=True, state=odd.tolist()),
        dict(device_session=42, server_session=43, epoch=1, period_us=1000, seq=2, cmd_seq=1, kind=0, fault=4,
             armed=False, state=[0.0] * DEV_NSTATE),
    ]


def _command_fields():
    return [
        dict(device_session=1, server_session=2, epoch=1, engagements=0, seq=1, state_seq=1, enable=True,
             wrench=[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
        dict(device_session=1_700_000_000_123_456_789, server_session=1_700_000_001_000_000_000, epoch=3,
             engagements=2, seq=99, state_seq=1234, enable=False, wrench=[0.0] * 6),
        dict(device_session=U64, server_session=U64, epoch=U32, engagements=U32, seq=U64, state_seq=U64, enable=True,
             wrench=[-10.0, 2.5, math.nan, math.inf, -math.inf, -0.0]),
    ]


def _old_state(f) -> bytes:
    buf = bytearray(R.STATE_SIZE)
    R.pack_state(buf, **f)
    return bytes(buf)


def _old_command(f) -> bytes:
    # RemoteDevice._send's own call (pack_command predates the engagements field)
    buf = bytearray(R.COMMAND_SIZE)
    R.COMMAND_HDR.pack_into(buf, 0, R.MAGIC, R.VERSION, R.T_COMMAND, R.F_ENABLE if f["enable"] else 0,
                            f["device_session"], f["server_session"], f["epoch"], f["engagements"], f["seq"],
                            f["state_seq"])
    np.frombuffer(buf, dtype="<f8", count=6, offset=R.COMMAND_HDR.size)[:] = f["wrench"]
    return bytes(buf)


class _Clock:
    def __init__(self):
        self.ns = 5_000_000_000

    def __call__(self):
        return self.ns


def _session() -> list[dict]:
    """A scripted exchange over loopback through a tap that records every datagram."""
    clock = _Clock()
    tap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tap.bind(("127.0.0.1", 0))
    tap.settimeout(5.0)
    srv = R.RemoteDevice(kind="planar", limits=R._sim.limits_of(R.RemotePlanar(), np.array([-0.06, -0.06, 0.0]),
                                                                np.array([0.06, 0.06, 0.0])),
                         listen=("127.0.0.1", 0), clock_ns=clock, session=1_700_000_000_000_000_000)
    sim = make_sim_device({"kind": "planar", "hand": {"type": "constant", "wrench": [0.0, 0.3, 0.0]}},
                          period_s=1e-3, clock_ns=clock)
    prog = R.DeviceProgram(sim, tap.getsockname(), watchdog_s=0.05, clock_ns=clock,
                           session=1_700_000_000_500_000_000)
    out = []
    row = np.zeros(DEV_NSTATE)

    def relay_state():
        data, _ = tap.recvfrom(4096)
        out.append({"dir": "state", "hex": data.hex()})
        tap.sendto(data, srv.local_address)

    try:
        # the server replies to the address the state came from: the tap; forward those to the device
        def step(wrench, *, engage=False, enable=False, disable=False):
            clock.ns += 1_000_000
            prog.tick()
            relay_state()
            srv.read(row)
            if engage:
                srv.on_engage()
            if enable:
                srv.enable()
            if disable:
                srv.disable()
                data, _ = tap.recvfrom(4096)
                out.append({"dir": "command", "hex": data.hex()})
                tap.sendto(data, prog.local_address)
            srv.write(np.array(wrench, dtype=float))
            data, _ = tap.recvfrom(4096)
            out.append({"dir": "command", "hex": data.hex()})
            tap.sendto(data, prog.local_address)

        for _ in range(2):
            step([0.0] * 6)
        step([0.5, 0.0, 0.0, 0.0, 0.0, 0.0], enable=True)
        for i in range(5):
            step([0.5, 0.1 * i, 0.0, 0.0, 0.0, 0.01], engage=(i == 2))
        step([0.0] * 6, disable=True)
        step([0.2, 0.0, 0.0, 0.0, 0.0, 0.0], enable=True)
        step([float("nan")] + [0.0] * 5)
        for _ in range(2):
            step([0.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    finally:
        prog.close()
        srv.close()
        tap.close()
    return out


def main() -> None:
    doc = {
        "state_size": R.STATE_SIZE, "command_size": R.COMMAND_SIZE,
        "state": [{"fields": f, "hex": _old_state(f).hex()} for f in _state_fields()],
        "command": [{"fields": f, "hex": _old_command(f).hex()} for f in _command_fields()],
        "session": _session(),
    }
    OUT.write_text(json.dumps(doc, indent=1, allow_nan=True) + "\n", encoding="utf-8")
    print(f"wrote {OUT}: {len(doc['state'])} states, {len(doc['command'])} commands, {len(doc['session'])} "
          "session datagrams")


if __name__ == "__main__":
    main()
