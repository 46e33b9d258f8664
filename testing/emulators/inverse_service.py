"""A fake Haply Inverse Service: the websocket JSON interface on 127.0.0.1, in its own process,
with the emulated Inverse3 of a shared block (:mod:`.block`) behind it.

As the service does (Haply's documentation of the Inverse Service, JSON format 3.0): on connect
it sends the inventory (``session_id``, ``inverse3[]`` with ``device_id``, ``config``, ``state``
``{cursor_position {x,y,z}, cursor_velocity {x,y,z}}``; ``wireless_verse_grip[]``), then exactly
one state frame (the same shape) per message the client sends, after applying that message's
commands (``{"inverse3": [{"device_id": ID, "commands": {"set_cursor_force": {"values":
{"x", "y", "z"}}}}]}``): the client sets the rate.

With ``--versegrip`` it lists one ``wireless_verse_grip`` too: ``state.orientation {w,x,y,z}`` (the
physics' handle orientation) and ``state.buttons {a,b,c}`` (the block's ``buttons`` bits 0-2).

Faults from the block: ``fault_unplugged`` -> the device is no longer listed in the frames;
``fault_error`` -> the frame lists it without a state; ``fault_frozen`` -> the physics stops
publishing (the same position comes back).

``python -m hapticproxy.testing.emulators.inverse_service BLOCK PORTFILE`` serves on a free port
(written to PORTFILE) until the block's ``stop`` slot is set or its parent dies.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np

from .block import OFFSETS, Block

DEVICE_ID = "049D"
GRIP_ID = "0A51"
#: list a wireless VerseGrip (orientation: the physics' handle orientation; buttons: the block's)
_VERSEGRIP = [False]


def _frame(block: Block, buf: np.ndarray, session: int, inventory: bool = False) -> str:
    o = OFFSETS
    b = block.b
    if b[o["fault_unplugged"]] != 0.0:
        devs = []
    else:
        block.read_state(buf)
        p = o["pos_m"] - o["time_s"]
        v = o["vel_m_s"] - o["time_s"]
        dev = {"device_id": DEVICE_ID}
        if b[o["fault_error"]] == 0.0:
            dev["state"] = {"cursor_position": dict(zip("xyz", map(float, buf[p:p + 3]))),
                            "cursor_velocity": dict(zip("xyz", map(float, buf[v:v + 3])))}
        if inventory:
            dev["config"] = {"device_info": {"id": DEVICE_ID, "model": "Inverse3"}}
        devs = [dev]
    grips = []
    if _VERSEGRIP[0] and b[o["fault_unplugged"]] == 0.0:
        q = o["quat"] - o["time_s"]
        bt = int(buf[o["buttons"] - o["time_s"]])
        grips = [{"device_id": GRIP_ID, "state": {
            "orientation": {"w": float(buf[q]), "x": float(buf[q + 1]), "y": float(buf[q + 2]), "z": float(buf[q + 3])},
            "buttons": {"a": bool(bt & 1), "b": bool(bt & 2), "c": bool(bt & 4)}}}]
    out = {"inverse3": devs, "wireless_verse_grip": grips}
    if inventory:
        out["session_id"] = session
    return json.dumps(out)


def _apply(block: Block, msg: str) -> None:
    o = OFFSETS
    b = block.b
    try:
        data = json.loads(msg)
    except ValueError:
        return
    for d in data.get("inverse3") or []:
        if d.get("device_id") != DEVICE_ID or b[o["fault_unplugged"]] != 0.0:
            continue
        f = ((d.get("commands") or {}).get("set_cursor_force") or {}).get("values")
        if f:
            b[o["cmd"]:o["cmd"] + 3] = (float(f.get("x", 0.0)), float(f.get("y", 0.0)), float(f.get("z", 0.0)))
            b[o["cmd"] + 3:o["cmd"] + 7] = 0.0
            b[o["cmd_seq"]] += 1.0
            b[o["force_on"]] = 1.0


def main(argv: list[str] | None = None) -> int:
    from websockets.sync.server import serve

    argv = sys.argv[1:] if argv is None else argv
    block = Block(argv[0])
    _VERSEGRIP[0] = "--versegrip" in argv[2:]
    parent = os.getppid()
    sessions = iter(range(1, 1 << 30))

    def handler(ws) -> None:
        buf = np.zeros(OFFSETS["buttons"] - OFFSETS["time_s"] + 1)
        session = next(sessions)
        ws.send(_frame(block, buf, session, inventory=True))
        for msg in ws:
            _apply(block, msg)
            ws.send(_frame(block, buf, session))

    with serve(handler, "127.0.0.1", 0, compression=None) as server:
        port = server.socket.getsockname()[1]
        tmp = argv[1] + ".part"
        with open(tmp, "w") as fh:
            fh.write(str(port))
        os.replace(tmp, argv[1])
        t = threading.Thread(target=server.serve_forever, daemon=True)
        t.start()
        while block["stop"] == 0.0 and os.getppid() == parent:
            time.sleep(0.05)
        server.shutdown()
    return 0


def spawn(block_path: str, folder: str, versegrip: bool = False) -> tuple[subprocess.Popen, str]:
    """Start the fake service in its own process (``versegrip``: with a wireless VerseGrip);
    returns it and its ``ws://`` URL."""
    portfile = os.path.join(folder, "service.port")
    proc = subprocess.Popen([sys.executable, "-m", "hapticproxy.testing.emulators.inverse_service", block_path,
                             portfile] + (["--versegrip"] if versegrip else []))
    end = time.monotonic() + 60.0
    while not os.path.exists(portfile):
        if proc.poll() is not None:
            raise RuntimeError(f"the Inverse Service fake exited with {proc.returncode}")
        if time.monotonic() > end:
            proc.kill()
            raise RuntimeError("the Inverse Service fake did not start within 60 s")
        time.sleep(0.01)
    return proc, f"ws://127.0.0.1:{open(portfile).read().strip()}"


if __name__ == "__main__":
    sys.exit(main())
