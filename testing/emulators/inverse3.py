"""A fake Haply Inverse3 on a pseudo-terminal, in its own process: the unmodified
``haplyhardwareapi`` package opens the terminal's path (``SerialStream(path)``) and talks the
device's serial framing to it; the handle's motion is the physics behind the shared block
(:mod:`.physics`, stepped by the test or by its own process).

Framing (host: one command byte + little-endian float32 values; device: one header byte +
payload), as the package speaks it:

=====================  ===========================  ==========================================
call                   host sends                   this device answers
=====================  ===========================  ==========================================
device_wakeup_dict()   0x0A                         0x0B + device id u16, model u8, hw u8, fw
                                                    u8, 16-byte UUID
end_effector_force(f)  0x2A + 3 f32 force [N]       0x2B + 6 f32: position [m], velocity [m/s]
end_effector_position  0x2C + 3 f32 position [m]    0x2B + 6 f32 (the command is held as zero
                                                    force: position control is not emulated)
=====================  ===========================  ==========================================

The device renders the last force it was sent until another arrives (no firmware watchdog is
emulated: none is documented for the Inverse3). Faults from the block: ``fault_unplugged`` -> it
stops answering (the host's read times out); ``fault_frozen`` -> the physics stops publishing,
so the same position comes back; ``fault_error`` -> it answers an unknown header byte
(0xEE, nothing after it) instead of the state; ``model_id`` is the model byte of the wake-up reply.

``python -m hapticproxy.testing.emulators.inverse3 BLOCK LINKFILE`` runs it: it opens a
pseudo-terminal, writes the path of its device side to LINKFILE, and serves until the block's
``stop`` slot is set or its parent dies.
"""
from __future__ import annotations

import os
import select
import struct
import subprocess
import sys
import termios
import time
import tty

from .block import OFFSETS, Block

WAKE, WAKE_REPLY = 0x0A, 0x0B
FORCE, POSITION, STATE = 0x2A, 0x2C, 0x2B
DEVICE_ID = 0x049D
_F3 = struct.Struct("<3f")
_STATE = struct.Struct("<B6f")


def serve(block: Block, master: int, parent: int) -> None:
    b = block.b
    buf = bytearray()
    o = OFFSETS
    last_check = time.monotonic()
    while b[o["stop"]] == 0.0:
        r, _, _ = select.select([master], [], [], 0.05)
        now = time.monotonic()
        if now - last_check > 0.5:
            last_check = now
            if os.getppid() != parent:
                return
        if not r:
            continue
        try:
            buf += os.read(master, 4096)
        except OSError:
            return
        while buf:
            cmd = buf[0]
            if cmd == WAKE:
                del buf[:1]
                if b[o["fault_unplugged"]] != 0.0:
                    continue
                uuid = bytes(range(16))
                os.write(master, struct.pack("<BHBBB", WAKE_REPLY, DEVICE_ID, int(b[o["model_id"]]) & 0xFF, 3, 7) + uuid)
            elif cmd in (FORCE, POSITION):
                if len(buf) < 13:
                    break
                f = _F3.unpack_from(buf, 1) if cmd == FORCE else (0.0, 0.0, 0.0)
                del buf[:13]
                if b[o["fault_unplugged"]] != 0.0:
                    continue
                b[o["cmd"]:o["cmd"] + 3] = f
                b[o["cmd"] + 3:o["cmd"] + 7] = 0.0
                b[o["cmd_seq"]] += 1.0
                b[o["force_on"]] = 1.0  # the Inverse3 has no separate enable: a force sent is rendered
                if b[o["fault_error"]] != 0.0:
                    os.write(master, bytes([0xEE]))
                    continue
                st = [0.0] * 6
                block.read_state(_state_buf)
                p = OFFSETS["pos_m"] - OFFSETS["time_s"]
                v = OFFSETS["vel_m_s"] - OFFSETS["time_s"]
                st[0:3] = _state_buf[p:p + 3]
                st[3:6] = _state_buf[v:v + 3]
                os.write(master, _STATE.pack(STATE, *st))
            else:
                del buf[:1]  # unknown command byte: skipped, as the device does


import numpy as _np  # noqa: E402

_state_buf = _np.zeros(OFFSETS["buttons"] - OFFSETS["time_s"] + 1)


def spawn(block_path: str, folder: str) -> tuple[subprocess.Popen, str]:
    """Start the fake in its own process; returns it and the path of its serial port."""
    link = os.path.join(folder, "inverse3.tty")
    proc = subprocess.Popen([sys.executable, "-m", "hapticproxy.testing.emulators.inverse3", block_path, link])
    end = time.monotonic() + 60.0
    while not os.path.exists(link) or not open(link).read().strip():
        if proc.poll() is not None:
            raise RuntimeError(f"the Inverse3 fake exited with {proc.returncode}")
        if time.monotonic() > end:
            proc.kill()
            raise RuntimeError("the Inverse3 fake did not open its pseudo-terminal within 60 s")
        time.sleep(0.01)
    return proc, open(link).read().strip()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    block = Block(argv[0])
    master, slave = os.openpty()
    tty.setraw(slave)
    attrs = termios.tcgetattr(slave)
    attrs[4] = attrs[5] = termios.B115200
    termios.tcsetattr(slave, termios.TCSANOW, attrs)
    path = os.ttyname(slave)
    tmp = argv[1] + ".part"
    with open(tmp, "w") as fh:
        fh.write(path)
    os.replace(tmp, argv[1])
    try:
        serve(block, master, os.getppid())
    finally:
        os.close(master)
        os.close(slave)
    return 0


if __name__ == "__main__":
    sys.exit(main())
