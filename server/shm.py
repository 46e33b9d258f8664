"""Shared memory between the haptic-loop process and its supervisor.

One ``multiprocessing.shared_memory`` block holds, as numpy views:

- ``status`` (float64[NSTAT]): live figures the loop publishes (steps, lateness, overruns, ...);
- ``hist_late`` / ``hist_step`` (int64[HBINS]): histograms of wake-up lateness and step compute
  time in 1 us bins (the last bin counts everything >= HBINS-1 us), from which percentiles are
  computed without the loop ever sorting anything;
- ``control`` (int64[NCTL]): requests from the supervisor (stop, re-arm, reset statistics), each
  a counter the supervisor increments and the loop acknowledges by copying it;
- ``ring`` (float64[rows, NTEL]) with ``head`` (rows ever written): the telemetry ring the
  supervisor drains to a file, so a crash of the loop process loses nothing already in it;
- ``translog`` (:data:`TRANSITION_DTYPE`[TLOG_ROWS]): the loop's last state transitions with
  their reasons (``lifecycle``), row ``seq % TLOG_ROWS``; the supervisor logs each one once.

The loop writes, the supervisor reads (except ``control``). Every field is a float64/int64 that
is written whole, so a reader sees either the old or the new value of each; percentiles read
while the loop runs are consistent to within one step.
"""
from __future__ import annotations

from multiprocessing import shared_memory

import numpy as np

from .lifecycle import LOOP_STATES, LS  # noqa: F401 - re-exported: the states live in lifecycle

HBINS = 4096
#: Rows of the transition log: more transitions than this between two reads of the supervisor
#: (every 50 ms) lose the oldest from the log, never from the counters.
TLOG_ROWS = 64
TRANSITION_DTYPE = np.dtype([("seq", np.int64), ("t_ns", np.int64), ("from_state", np.int64),
                             ("to_state", np.int64), ("reason", np.int64), ("detail", np.float64)])

STATUS_FIELDS = (
    "pid", "steps", "rate_hz", "period_ns", "t_start_ns", "t_last_ns", "rt_scheduling",
    "lateness_max_us", "compute_max_us", "overruns", "missed_deadlines", "updates", "acks_sent",
    "stale_or_duplicate", "decode_errors", "dropped_packets", "contacts", "session_id", "sessions_opened",
    "loop_state", "watchdog", "gain", "fault", "device_fault", "model_nonfinite", "saturated", "rate_limited",
    "speed_trips", "spin_ns", "env_silence_ms", "env_rate_hz", "ready", "exit_code", "timer_slack",
    "force_cap_n", "rate_limit_n_per_step", "engagements", "faults_total", "telemetry_overwritten",
    # what the session layer refused, by reason (stale_or_duplicate and decode_errors above)
    "datagrams_received", "bad_token", "wrong_peer", "unknown_session", "bad_mac", "unexpected",
    "wrong_version", "rejects_sent", "dropped_empty", "poll_budget_cuts",
    # lifecycle: transitions written to the log, stall trips (device watchdog cut by a late
    # loop), recoveries from them, kernels compiled after the loop was armed (must stay 0)
    "transitions", "stall_trips", "stall_recoveries", "late_compiles",
)
ST = {name: i for i, name in enumerate(STATUS_FIELDS)}
NSTAT = len(STATUS_FIELDS)

CONTROL_FIELDS = ("stop", "stop_ack", "rearm", "rearm_ack", "reset_stats", "reset_ack")
CT = {name: i for i, name in enumerate(CONTROL_FIELDS)}
NCTL = len(CONTROL_FIELDS)


_AX6 = ("fx", "fy", "fz", "tx", "ty", "tz")
TEL_FIELDS = (
    ("t_s", "lateness_us", "compute_us", "loop_state", "gain", "contacts", "updates")
    + tuple(f"dev_{a}" for a in ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz"))
    + tuple(f"proxy_{a}" for a in ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz"))
    + tuple(f"cmd_{a}" for a in _AX6)      # command written to the device, device frame
    + tuple(f"env_{a}" for a in _AX6)      # environment wrench at the hand point, world
    + tuple(f"hand_{a}" for a in _AX6)     # measured hand wrench, device frame (NaN: no sensor)
    + tuple(f"couple_{a}" for a in _AX6)   # position-channel wrench on the proxy, world
)
TEL = {name: i for i, name in enumerate(TEL_FIELDS)}
NTEL = len(TEL_FIELDS)


class SharedState:
    """The shared block and its numpy views. ``create`` in the supervisor, ``attach`` in the loop.

    The same class works without shared memory (``local=True``) for in-process loops and tests.
    """

    def __init__(self, ring_rows: int, shm: shared_memory.SharedMemory | None) -> None:
        self.ring_rows = int(ring_rows)
        self._shm = shm
        sizes = [NSTAT * 8, 2 * HBINS * 8, NCTL * 8, 8, TLOG_ROWS * TRANSITION_DTYPE.itemsize,
                 self.ring_rows * NTEL * 8]
        total = sum(sizes)
        buf = shm.buf if shm is not None else memoryview(bytearray(total))
        self._buf = buf
        off = 0
        self.status = np.ndarray((NSTAT,), np.float64, buf, off); off += sizes[0]
        hist = np.ndarray((2, HBINS), np.int64, buf, off); off += sizes[1]
        self.hist_late = hist[0]
        self.hist_step = hist[1]
        self.control = np.ndarray((NCTL,), np.int64, buf, off); off += sizes[2]
        self.head = np.ndarray((1,), np.int64, buf, off); off += sizes[3]
        self.translog = np.ndarray((TLOG_ROWS,), TRANSITION_DTYPE, buf, off); off += sizes[4]
        self.ring = np.ndarray((self.ring_rows, NTEL), np.float64, buf, off)

    @staticmethod
    def nbytes(ring_rows: int) -> int:
        return NSTAT * 8 + 2 * HBINS * 8 + NCTL * 8 + 8 + TLOG_ROWS * TRANSITION_DTYPE.itemsize + int(ring_rows) * NTEL * 8

    @classmethod
    def create(cls, ring_rows: int) -> "SharedState":
        shm = shared_memory.SharedMemory(create=True, size=cls.nbytes(ring_rows))
        s = cls(ring_rows, shm)
        s.status[:] = 0.0
        s.hist_late[:] = 0
        s.hist_step[:] = 0
        s.control[:] = 0
        s.head[0] = 0
        s.translog[:] = np.zeros(TLOG_ROWS, TRANSITION_DTYPE)
        return s

    @classmethod
    def attach(cls, name: str, ring_rows: int) -> "SharedState":
        # The supervisor owns the block. Under the spawn start method the loop process shares
        # the supervisor's resource tracker, so attaching registers nothing new to unlink.
        shm = shared_memory.SharedMemory(name=name)
        return cls(ring_rows, shm)

    @classmethod
    def local(cls, ring_rows: int) -> "SharedState":
        return cls(ring_rows, None)

    @property
    def name(self) -> str | None:
        return self._shm.name if self._shm is not None else None

    def close(self, unlink: bool = False) -> None:
        if self._shm is None:
            return
        # drop the views before closing the mapping
        self.status = self.hist_late = self.hist_step = self.control = self.head = self.ring = self.translog = None
        self._buf = None
        try:
            self._shm.close()
        except BufferError:
            pass
        if unlink:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass
        self._shm = None

    # ------------------------------------------------------------------ reading helpers
    def get(self, name: str) -> float:
        return float(self.status[ST[name]])

    def snapshot(self) -> dict:
        """Status as a dict, with lateness/compute percentiles from the histograms."""
        out = {name: float(self.status[i]) for i, name in enumerate(STATUS_FIELDS)}
        for key, hist in (("lateness_us", self.hist_late), ("compute_us", self.hist_step)):
            out[key] = percentiles(hist)
        out["loop_state"] = LOOP_STATES[int(out["loop_state"])] if 0 <= out["loop_state"] < len(LOOP_STATES) else "?"
        return out

    def log_transition(self, t_ns: int, from_state: float, to_state: float, reason: int, detail: float) -> None:
        """Append one transition (the loop; the supervisor reads them with ``transitions_since``).
        The row is written before ``status.transitions`` counts it, so a reader never sees a
        counted row half written."""
        seq = int(self.status[ST["transitions"]]) + 1
        self.translog[seq % TLOG_ROWS] = (seq, t_ns, int(from_state), int(to_state), int(reason), float(detail))
        self.status[ST["transitions"]] = seq

    def transitions_since(self, seq: int) -> list[tuple]:
        """Transitions logged after ``seq`` (oldest first; at most the last TLOG_ROWS)."""
        last = int(self.status[ST["transitions"]])
        first = max(seq + 1, last - TLOG_ROWS + 1)
        out = []
        for k in range(first, last + 1):
            r = self.translog[k % TLOG_ROWS]
            if int(r["seq"]) == k:
                out.append((k, int(r["t_ns"]), int(r["from_state"]), int(r["to_state"]), int(r["reason"]),
                            float(r["detail"])))
        return out

    def request(self, name: str) -> int:
        self.control[CT[name]] += 1
        return int(self.control[CT[name]])


def percentiles(hist: np.ndarray, qs=(0.5, 0.99, 0.999)) -> dict:
    """Percentiles (us, bin upper edges) of a 1-us histogram; ``max`` is the highest bin hit."""
    h = np.asarray(hist, dtype=np.int64).copy()
    n = int(h.sum())
    out: dict = {"count": n}
    if n == 0:
        for q in qs:
            out[_qname(q)] = None
        out["max"] = None
        return out
    cum = np.cumsum(h)
    for q in qs:
        idx = int(np.searchsorted(cum, q * n, side="left"))
        out[_qname(q)] = float(min(idx, HBINS - 1) + 1)
    out["max"] = float(np.nonzero(h)[0][-1] + 1)
    return out


def _qname(q: float) -> str:
    s = f"{q * 100:g}".replace(".", "")
    return f"p{s}"
