"""The shared block between an emulated device's physics and the front ends that fake its SDK.

One file of float64 slots (``mmap``-ed by the physics, by the fake ``libdrd.so`` / ``libHD.so``
and by the Inverse3 and Inverse Service fakes): the device's state, written by the physics only,
and the host's command and switches, written by the front end only; faults are injected by the
test writing the ``fault_*`` slots. The layout is declared once here (:data:`SLOTS`); the C front
ends get it as ``#define`` lines generated from this table (:func:`c_header`).

Who writes what, and why a reader never sees a torn sample:

- the state (``time_s`` .. ``buttons``) is written by the physics under a sequence lock:
  ``state_seq`` odd while it writes, even (and one more) when done; a reader copies the state,
  re-reads the counter and retries when it changed or was odd. Only the physics writes it.
- the command (``cmd``, ``cmd_gripper_n``) is written by the one front end that opened the device
  (``owner_pid``), then ``cmd_seq`` is incremented: the physics reads ``cmd_seq``, the command,
  and ``cmd_seq`` again, and keeps the previous command when they differ (it tries again at its
  next tick, 1 ms later). ``cmd_seq`` advancing is also what the device's firmware watchdog sees.
- single float64 slots (switches, counters, faults) are written whole by one side (x86-64 stores
  of aligned 8-byte words are atomic).
"""
from __future__ import annotations

import mmap
import os

import numpy as np

MAGIC = 0x48505845  # "HPXE"
LAYOUT_VERSION = 2

#: (name, count, meaning); ``[x]`` = who writes it: P physics, F front end, T the test
SLOTS: tuple[tuple[str, int, str], ...] = (
    ("magic", 1, "MAGIC [P]"),
    ("layout_version", 1, "LAYOUT_VERSION [P]"),
    ("state_seq", 1, "sequence lock of the state below: odd while the physics writes it [P]"),
    ("time_s", 1, "device time [s] [P]"),
    ("pos_m", 3, "handle position, device frame [m] [P]"),
    ("quat", 4, "handle orientation qw qx qy qz [P]"),
    ("vel_m_s", 3, "linear velocity [m/s] [P]"),
    ("angvel_rad_s", 3, "angular velocity [rad/s] [P]"),
    ("gripper_rad", 1, "gripper opening angle [rad] [P]"),
    ("gripper_rad_s", 1, "gripper opening rate [rad/s] [P]"),
    ("buttons", 1, "button bit mask [P]"),
    ("cmd_seq", 1, "incremented after each command write [F]"),
    ("cmd", 6, "commanded force [N] and torque [N m], device frame [F]"),
    ("cmd_gripper_n", 1, "commanded gripper force [N] [F]"),
    ("force_on", 1, "1: the host enabled forces (dhdEnableForce, hdEnable); the physics clears it on a cut [F, P]"),
    ("force_off_cause", 1, "why forces went off last: 0 none, 3 watchdog, 4 software, 5 USB disconnect [P, F]"),
    ("watchdog_s", 1, "the firmware watchdog the host set (0: none) [F]"),
    ("watchdog_trips", 1, "firmware watchdog cuts [P]"),
    ("rendered", 6, "the wrench the motors render now (after force_on, the cut, the model's caps) [P]"),
    ("saturated", 1, "ticks whose command the model's force cap scaled down [P]"),
    ("calibrated", 1, "1: calibrated (drdAutoInit done, or the model needs none) [F]"),
    ("owner_pid", 1, "pid of the process that opened the device (0: free) [F]"),
    ("model_id", 1, "the model the device says it is (FD system type; Touch / Inverse3: index in the header table) [T]"),
    ("serial", 1, "serial number [T]"),
    ("fault_unplugged", 1, "1: the device is gone (calls fail with the SDK's communication error) [T]"),
    ("fault_frozen", 1, "1: the state stops updating (a stuck sensor / hung firmware) [T]"),
    ("fault_late_ms", 1, "the servo thread oversleeps by this many ms per tick (device-clocked SDKs) [T]"),
    ("fault_error", 1, "non-zero: every device call fails with this SDK error code [T]"),
    ("hand_go", 1, "incremented by the test: the scripted hand starts its script (as on_engage does) [T]"),
    ("steps", 1, "physics steps taken [P]"),
    ("period_s", 1, "the physics period [s] [P]"),
    ("stop", 1, "1: the physics process exits [T]"),
    ("alive", 1, "1 while a physics process runs [P]"),
    ("servo_ticks", 1, "servo-thread ticks (libHD fake) [F]"),
    ("servo_late", 1, "servo ticks that started more than one period late [F]"),
    ("servo_max_late_us", 1, "the latest servo tick start [us] [F]"),
)

OFFSETS: dict[str, int] = {}
_n = 0
for _name, _count, _doc in SLOTS:
    OFFSETS[_name] = _n
    _n += _count
NSLOTS = _n
#: the state columns the sequence lock covers (time_s .. buttons)
STATE_FIRST = OFFSETS["time_s"]
STATE_LAST = OFFSETS["buttons"]
BLOCK_BYTES = 8 * NSLOTS


def c_header() -> str:
    """``#define B_<NAME> <offset>`` for every slot (the C front ends' view of :data:`SLOTS`)."""
    lines = ["/* generated from hapticproxy.testing.emulators.block.SLOTS: do not edit */",
             f"#define B_MAGIC_VALUE {MAGIC}", f"#define B_LAYOUT_VERSION_VALUE {LAYOUT_VERSION}",
             f"#define B_NSLOTS {NSLOTS}", f"#define B_STATE_FIRST {STATE_FIRST}", f"#define B_STATE_LAST {STATE_LAST}"]
    lines += [f"#define B_{name.upper()} {OFFSETS[name]}  /* {doc} */" for name, _c, doc in SLOTS]
    return "\n".join(lines) + "\n"


class Block:
    """A block file mapped into this process: ``b[OFFSETS["pos_m"]]`` or :meth:`view`."""

    def __init__(self, path: str, *, create: bool = False) -> None:
        self.path = str(path)
        if create:
            with open(self.path, "wb") as fh:
                fh.write(b"\0" * BLOCK_BYTES)
        fd = os.open(self.path, os.O_RDWR)
        try:
            self._mm = mmap.mmap(fd, BLOCK_BYTES)
        finally:
            os.close(fd)
        self.b = np.frombuffer(self._mm, dtype=np.float64, count=NSLOTS)
        if create:
            self.b[OFFSETS["magic"]] = MAGIC
            self.b[OFFSETS["layout_version"]] = LAYOUT_VERSION
            self.b[OFFSETS["quat"]] = 1.0
            self.b[OFFSETS["calibrated"]] = 1.0

    def view(self, name: str) -> np.ndarray:
        """The slots of ``name`` (a view: writes go to the block)."""
        o = OFFSETS[name]
        return self.b[o:o + dict((n, c) for n, c, _ in SLOTS)[name]]

    def __getitem__(self, name: str) -> float:
        return float(self.b[OFFSETS[name]])

    def __setitem__(self, name: str, value: float) -> None:
        self.b[OFFSETS[name]] = value

    def read_state(self, out: np.ndarray) -> None:
        """Copy the state slots (``time_s`` .. ``buttons``) into ``out`` under the sequence lock."""
        b = self.b
        seq_i = OFFSETS["state_seq"]
        while True:
            s1 = b[seq_i]
            if int(s1) & 1:
                continue
            out[:] = b[STATE_FIRST:STATE_LAST + 1]
            if b[seq_i] == s1:
                return

    def close(self) -> None:
        self.b = None  # type: ignore[assignment]
        try:
            self._mm.close()
        except BufferError:  # a view is still held somewhere: the mapping goes with the process
            pass
