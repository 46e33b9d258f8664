"""Shared memory between the haptic-loop process and its supervisor.

One ``multiprocessing.shared_memory`` block holds, as numpy views, every part declared once as a
numpy (structured) dtype, so a field is named where it is written and where it is read and a
misspelt one fails (numba refuses an unknown record field when it compiles):

- ``stat`` (:data:`STATUS_DTYPE`, one record) with ``status``, the same memory as float64[NSTAT]
  (``status[ST[name]]``): live figures the loop publishes (steps, lateness, overruns, ...);
- ``hist_late`` / ``hist_step`` (int64[HBINS]): histograms of wake-up lateness and step compute
  time in 1 us bins (the last bin counts everything >= HBINS-1 us), from which percentiles are
  computed without the loop ever sorting anything;
- ``control`` (int64[NCTL]): requests from the supervisor (stop, re-arm, reset statistics), each
  a counter the supervisor increments and the loop acknowledges by copying it;
- ``tel`` (:data:`TEL_DTYPE`[rows]) with ``ring``, the same memory as float64[rows, NTEL]
  (``ring[:, TEL[name]]``), and ``head`` (rows ever written): the telemetry ring, one row per
  haptic step, that the supervisor drains to a recording, so a crash of the loop process loses
  nothing already in it;
- the contact ring, one row per applied model update (30-60 Hz, not per haptic step):
  ``contact_hdr`` (:data:`CONTACT_HDR_DTYPE`[CONTACT_ROWS]: time, count, ...) and the update's
  contacts ``contact_key`` (int64[CONTACT_ROWS, MAX_CONTACTS, 3]), ``contact_position_m``,
  ``contact_normal`` (float64[..., 3]), ``contact_separation_m`` (float64[CONTACT_ROWS,
  MAX_CONTACTS]), with ``contact_head`` (rows ever written); a row's ``seq`` is -1 while the loop
  writes it, so a reader that copied it while it changed sees a different ``seq`` and drops it;
- ``translog`` (:data:`TRANSITION_DTYPE`[TLOG_ROWS]): the loop's last state transitions with
  their reasons (``lifecycle``), row ``seq % TLOG_ROWS``; the supervisor logs each one once.

The loop writes, the supervisor reads (except ``control``). Every field is a float64/int64 that
is written whole, so a reader sees either the old or the new value of each; percentiles read
while the loop runs are consistent to within one step. The kernels that write the rings are in
``rings`` (this module imports no numba: ``hapticproxy status`` reads these names too).
"""
from __future__ import annotations

import math
from multiprocessing import shared_memory

import numpy as np

from .lifecycle import LOOP_STATES, LS  # noqa: F401 - re-exported: the states live in lifecycle

HBINS = 4096
#: Rows of the transition log: more transitions than this between two reads of the supervisor
#: (every 50 ms) lose the oldest from the log, never from the counters.
TLOG_ROWS = 64
TRANSITION_DTYPE = np.dtype([("seq", np.int64), ("t_ns", np.int64), ("from_state", np.int64),
                             ("to_state", np.int64), ("reason", np.int64), ("detail", np.float64)])

# ---------------------------------------------------------------------------- status block
#: (name, kind): every field is stored as float64 (written whole by the loop); "i" fields are
#: counts, codes or flags and are reported as JSON integers, "f" fields as numbers.
STATUS_LAYOUT = (
    ("pid", "i"), ("steps", "i"), ("rate_hz", "f"), ("period_ns", "i"), ("t_start_ns", "i"), ("t_last_ns", "i"),
    ("rt_scheduling", "i"), ("lateness_max_us", "f"), ("compute_max_us", "f"), ("overruns", "i"),
    ("missed_deadlines", "i"), ("updates", "i"), ("acks_sent", "i"), ("stale_or_duplicate", "i"),
    ("decode_errors", "i"), ("dropped_packets", "i"), ("contacts", "i"), ("session_id", "i"),
    ("sessions_opened", "i"), ("loop_state", "i"), ("watchdog", "i"), ("gain", "f"), ("fault", "i"),
    ("device_fault", "i"), ("model_nonfinite", "i"), ("saturated", "i"), ("rate_limited", "i"),
    ("speed_trips", "i"), ("spin_ns", "i"), ("env_silence_ms", "f"), ("env_rate_hz", "f"), ("ready", "i"),
    ("exit_code", "i"), ("timer_slack", "i"), ("force_cap_n", "f"), ("rate_limit_n_per_step", "f"),
    ("engagements", "i"), ("faults_total", "i"), ("telemetry_overwritten", "i"),
    # what the session layer refused, by reason (stale_or_duplicate and decode_errors above)
    ("datagrams_received", "i"), ("bad_token", "i"), ("wrong_peer", "i"), ("unknown_session", "i"),
    ("bad_mac", "i"), ("unexpected", "i"), ("wrong_version", "i"), ("rejects_sent", "i"), ("dropped_empty", "i"),
    ("poll_budget_cuts", "i"),
    # lifecycle: transitions written to the log, stall trips (device watchdog cut by a late
    # loop), recoveries from them, kernels compiled after the loop was armed (must stay 0)
    ("transitions", "i"), ("stall_trips", "i"), ("stall_recoveries", "i"), ("late_compiles", "i"),
    # the cap on the torque's norm (the force's is above), N m
    ("torque_cap_n_m", "f"),
    # ContactUpdates refused before the model (answered with an Error naming the field): outside
    # the scene's bounds (Welcome), contacts the tool cannot use, a sequence number jumping ahead
    ("refused_out_of_bounds", "i"), ("refused_unusable", "i"), ("refused_seq_jump", "i"),
    # the model: reversed normals refused, renumbered keys continued, contacts being recovered,
    # the work the deformation recovery did on the hand [J]; the engine's advice [m, s];
    # reversed normals taken (the held contact had the tool behind it, or the reversal outlasted
    # the refusals); times the proxy's integration diverged (lifecycle.FAULT_POLICY "diverged")
    ("flips_refused", "i"), ("rekeyed", "i"), ("recovering", "i"), ("recovery_energy_j", "f"),
    ("flips_taken", "i"), ("diverged", "i"),
    ("advised_epsilon_m", "f"), ("advised_lead_s", "f"),
    # the port the loop's transport bound (a configured port 0 is the system's pick), 0: none
    ("transport_port", "i"),
    # who ran the ticks: the compiled loop on its own (the rest were steps Python ran), or the
    # device's servo thread (device-clocked: ticks it ran, and ticks it held while Python changed
    # the tick's state, writing the previous command again)
    ("ticks_compiled", "i"), ("servo_ticks", "i"), ("servo_held", "i"),
    # the energy the device gave the hand since start (the ledger at the hand's port: each
    # command held over its period times the handle's displacement during it), J
    ("energy_hand_j", "f"),
    # the passivity layer (server/passivity.py): its tank level [J], the steps it limited the
    # command, the lowest level the tank reached [J]
    ("tank_j", "f"), ("passivity_limited", "i"), ("tank_low_j", "f"),
    # the engaged tool as its Hello declared it (``publish_tool``, read by ``engaged_tool``):
    # its number (the engagement that wrote it; -1 while written, 0 none yet), kind (vocab
    # ToolKind), mass [kg], centre of mass [m, tool frame], inertia [Ixx Iyy Izz Ixy Ixz Iyz, kg m^2]
    ("tool_seq", "i"), ("tool_kind", "i"), ("tool_mass_kg", "f"), ("tool_com_x_m", "f"), ("tool_com_y_m", "f"),
    ("tool_com_z_m", "f"), ("tool_ixx_kg_m2", "f"), ("tool_iyy_kg_m2", "f"), ("tool_izz_kg_m2", "f"),
    ("tool_ixy_kg_m2", "f"), ("tool_ixz_kg_m2", "f"), ("tool_iyz_kg_m2", "f"),
    # contacts whose constraint's advance into the tool the passivity layer held back at the
    # last step (set-position modulation, ``kernels._hold``)
    ("held", "i"),
    # the idle CPUs' wake-up latency the loop holds the kernel to ([loop] cpu_latency_us), us;
    # -1: none held (off, the simulated clock, or refused: the daemon's log says why)
    ("cpu_latency_us", "i"),
    # the CPU the clock thread ticks on ([loop] clock_cpu); -1: not pinned, or no clock thread
    ("clock_cpu", "i"),
)
_TOOL_FIELDS = ("tool_kind", "tool_mass_kg", "tool_com_x_m", "tool_com_y_m", "tool_com_z_m", "tool_ixx_kg_m2",
                "tool_iyy_kg_m2", "tool_izz_kg_m2", "tool_ixy_kg_m2", "tool_ixz_kg_m2", "tool_iyz_kg_m2")
STATUS_DTYPE = np.dtype([(name, np.float64) for name, _ in STATUS_LAYOUT])
STATUS_FIELDS = STATUS_DTYPE.names
#: status field -> index into the float64 view ``SharedState.status``
ST = {name: STATUS_DTYPE.fields[name][1] // 8 for name in STATUS_FIELDS}
NSTAT = len(STATUS_FIELDS)
STATUS_INT_FIELDS = frozenset(name for name, kind in STATUS_LAYOUT if kind == "i")

CONTROL_FIELDS = ("stop", "stop_ack", "rearm", "rearm_ack", "reset_stats", "reset_ack")
CT = {name: i for i, name in enumerate(CONTROL_FIELDS)}
NCTL = len(CONTROL_FIELDS)

# ---------------------------------------------------------------------------- telemetry row
_AX6 = ("fx", "fy", "fz", "tx", "ty", "tz")
_POSE13 = ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")
#: Scalar columns of a telemetry row, then its vectors with their components' names. The flat
#: names (``dev_x``, ``cmd_fy``, ...) index the float64 view: ``ring[:, TEL["cmd_fy"]]``.
#: ``seq`` is the row's number (as ``head`` counts), -1 while the loop writes it: a seqlock, so a
#: reader that copied a row while it was rewritten (the ring lapped it) can tell (``rows``).
TEL_SCALARS = ("t_s", "lateness_us", "compute_us", "loop_state", "gain", "contacts", "updates", "seq", "energy_hand_j",
               "tank_j")
TEL_VECTORS = (
    ("dev", _POSE13),     # device handle pose (x y z qw qx qy qz) and twist, world
    ("proxy", _POSE13),   # proxy hand-point pose and twist, world, after the step
    ("cmd", _AX6),        # command written to the device, device frame
    ("env", _AX6),        # environment wrench at the hand point, world
    ("hand", _AX6),       # measured hand wrench, device frame (NaN: no sensor)
    ("couple", _AX6),     # position-channel wrench on the proxy, world
)
TEL_DTYPE = np.dtype([(n, np.float64) for n in TEL_SCALARS] + [(n, np.float64, (len(c),)) for n, c in TEL_VECTORS])
TEL_FIELDS = TEL_SCALARS + tuple(f"{n}_{c}" for n, comps in TEL_VECTORS for c in comps)
TEL = {name: i for i, name in enumerate(TEL_FIELDS)}
NTEL = len(TEL_FIELDS)
assert TEL_DTYPE.itemsize == 8 * NTEL
assert all(TEL_DTYPE.fields[n][1] // 8 == TEL[f"{n}_{c[0]}"] for n, c in TEL_VECTORS)

# ---------------------------------------------------------------------------- contact ring
#: Contacts kept per contact-ring row: the config's largest ``model.capacity``; an update with
#: more (never granted by the handshake) keeps its first MAX_CONTACTS and its true ``count``.
MAX_CONTACTS = 64
#: Rows of the contact ring: 8.5 s of updates at 60 Hz; the supervisor reads it every 50 ms.
CONTACT_ROWS = 512
CONTACT_HDR_DTYPE = np.dtype([
    ("seq", np.int64),          # update number this row holds (-1 while the loop writes it)
    ("t_s", np.float64),        # loop time of the step that applied it (the telemetry rows' t_s)
    ("env_time_s", np.float64),  # the engine's simulation time of the update
    ("update", np.int64),       # the loop's update counter after it (telemetry ``updates``)
    ("count", np.int64),        # contacts in the update
])


def _align(n: int) -> int:
    return (n + 63) // 64 * 64


def _layout(ring_rows: int) -> tuple[list[tuple[str, int]], int]:
    parts = [
        ("stat", STATUS_DTYPE.itemsize), ("hist", 2 * HBINS * 8), ("control", NCTL * 8), ("head", 8),
        ("translog", TLOG_ROWS * TRANSITION_DTYPE.itemsize), ("contact_head", 8),
        ("contact_hdr", CONTACT_ROWS * CONTACT_HDR_DTYPE.itemsize),
        ("contact_key", CONTACT_ROWS * MAX_CONTACTS * 3 * 8), ("contact_position_m", CONTACT_ROWS * MAX_CONTACTS * 3 * 8),
        ("contact_normal", CONTACT_ROWS * MAX_CONTACTS * 3 * 8), ("contact_separation_m", CONTACT_ROWS * MAX_CONTACTS * 8),
        ("tel", int(ring_rows) * TEL_DTYPE.itemsize),
    ]
    out, off = [], 0
    for name, size in parts:
        out.append((name, off))
        off = _align(off + size)
    return out, off


class SharedState:
    """The shared block and its numpy views. ``create`` in the supervisor, ``attach`` in the loop.

    The same class works without shared memory (``local=True``) for in-process loops and tests.
    """

    def __init__(self, ring_rows: int, shm: shared_memory.SharedMemory | None) -> None:
        self.ring_rows = int(ring_rows)
        self._shm = shm
        offs, total = _layout(self.ring_rows)
        buf = shm.buf if shm is not None else memoryview(bytearray(total))
        self._buf = buf
        o = dict(offs)
        self.stat = np.ndarray((1,), STATUS_DTYPE, buf, o["stat"])
        self.status = np.ndarray((NSTAT,), np.float64, buf, o["stat"])
        hist = np.ndarray((2, HBINS), np.int64, buf, o["hist"])
        self.hist_late = hist[0]
        self.hist_step = hist[1]
        self.control = np.ndarray((NCTL,), np.int64, buf, o["control"])
        self.head = np.ndarray((1,), np.int64, buf, o["head"])
        self.translog = np.ndarray((TLOG_ROWS,), TRANSITION_DTYPE, buf, o["translog"])
        self.contact_head = np.ndarray((1,), np.int64, buf, o["contact_head"])
        self.contact_hdr = np.ndarray((CONTACT_ROWS,), CONTACT_HDR_DTYPE, buf, o["contact_hdr"])
        self.contact_key = np.ndarray((CONTACT_ROWS, MAX_CONTACTS, 3), np.int64, buf, o["contact_key"])
        self.contact_position_m = np.ndarray((CONTACT_ROWS, MAX_CONTACTS, 3), np.float64, buf, o["contact_position_m"])
        self.contact_normal = np.ndarray((CONTACT_ROWS, MAX_CONTACTS, 3), np.float64, buf, o["contact_normal"])
        self.contact_separation_m = np.ndarray((CONTACT_ROWS, MAX_CONTACTS), np.float64, buf, o["contact_separation_m"])
        self.tel = np.ndarray((self.ring_rows,), TEL_DTYPE, buf, o["tel"])
        self.ring = np.ndarray((self.ring_rows, NTEL), np.float64, buf, o["tel"])
        #: telemetry rows a reader found torn or rewritten while it copied them (dropped)
        self.torn_rows = 0

    @property
    def contacts(self) -> tuple:
        """The contact ring as the tuple ``rings.record_contacts`` writes."""
        return (self.contact_hdr, self.contact_key, self.contact_position_m, self.contact_normal,
                self.contact_separation_m, self.contact_head)

    @staticmethod
    def nbytes(ring_rows: int) -> int:
        return _layout(ring_rows)[1]

    @classmethod
    def create(cls, ring_rows: int) -> "SharedState":
        shm = shared_memory.SharedMemory(create=True, size=cls.nbytes(ring_rows))
        s = cls(ring_rows, shm)
        s._buf[:] = b"\0" * len(s._buf)  # zero every part (a fresh mapping is, but say so)
        s.contact_hdr["seq"] = -1
        s.status[ST["cpu_latency_us"]] = -1.0
        s.status[ST["clock_cpu"]] = -1.0
        return s

    @classmethod
    def attach(cls, name: str, ring_rows: int) -> "SharedState":
        # The supervisor owns the block. Under the spawn start method the loop process shares
        # the supervisor's resource tracker, so attaching registers nothing new to unlink.
        shm = shared_memory.SharedMemory(name=name)
        return cls(ring_rows, shm)

    @classmethod
    def local(cls, ring_rows: int) -> "SharedState":
        s = cls(ring_rows, None)
        s.contact_hdr["seq"] = -1
        s.status[ST["cpu_latency_us"]] = -1.0
        s.status[ST["clock_cpu"]] = -1.0
        return s

    @property
    def name(self) -> str | None:
        return self._shm.name if self._shm is not None else None

    def close(self, unlink: bool = False) -> None:
        if self._shm is None:
            return
        # drop the views before closing the mapping
        for attr in ("stat", "status", "hist_late", "hist_step", "control", "head", "translog", "contact_head",
                     "contact_hdr", "contact_key", "contact_position_m", "contact_normal", "contact_separation_m",
                     "tel", "ring"):
            setattr(self, attr, None)
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
        """Status as a dict of JSON-ready values: counts as ints, figures as floats, a value that
        is not known (NaN, the silence before any update) as ``None``; lateness/compute
        percentiles from the histograms; the state by name."""
        out: dict = {}
        for i, name in enumerate(STATUS_FIELDS):
            v = float(self.status[i])
            if not math.isfinite(v):
                out[name] = None
            elif name in STATUS_INT_FIELDS:
                out[name] = int(v)
            else:
                out[name] = v
        if out.get("env_silence_ms") is not None and out["env_silence_ms"] < 0:
            out["env_silence_ms"] = None  # no update yet
        for key, hist in (("lateness_us", self.hist_late), ("compute_us", self.hist_step)):
            out[key] = percentiles(hist)
        code = out["loop_state"]
        out["loop_state"] = LOOP_STATES[code] if code is not None and 0 <= code < len(LOOP_STATES) else "?"
        return out

    def latest_row(self) -> np.ndarray | None:
        """The newest complete telemetry row (a copy of the structured record), or None before the
        first."""
        head = int(self.head[0])
        if head <= 0:
            return None
        got = self.rows(max(0, head - 2), head)
        return got[-1].copy() if len(got) else None

    def catch_up(self, read: int) -> tuple[int, int, int]:
        """For a reader that has consumed telemetry rows up to ``read`` (absolute, as ``head``
        counts): ``(start, head, lost)``, the oldest row it can still read (``read``, or the
        oldest in the ring when it fell further behind), the head, and the rows it lost."""
        head = int(self.head[0])
        lost = max(0, head - read - self.ring_rows)
        return read + lost, head, lost

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Telemetry rows ``start..stop-1`` (absolute numbers, as ``head`` counts; both within the
        last ``ring_rows``), oldest first, as a structured copy: only rows that are complete and
        were not rewritten while they were copied (the seqlock's check; ``torn_rows`` counts the
        others). The loop writes a row's ``seq`` as -1, then its fields, then its number, with a
        fence between each (``rings.account``); this side copies, then reads ``seq`` again. On
        x86-64 loads are not reordered with loads, so the copy's ``seq`` and the second read
        bracket the copy."""
        rows = self.ring_rows
        i0, n = start % rows, stop - start
        if n <= 0:
            return np.zeros(0, TEL_DTYPE)
        if i0 + n <= rows:
            idx = slice(i0, i0 + n)
            out = self.tel[idx].copy()
            after = self.tel["seq"][idx].copy()
        else:
            out = np.concatenate([self.tel[i0:], self.tel[: i0 + n - rows]])
            after = np.concatenate([self.tel["seq"][i0:], self.tel["seq"][: i0 + n - rows]])
        want = np.arange(start, stop, dtype=np.float64)
        ok = (out["seq"] == want) & (after == want)
        bad = n - int(np.count_nonzero(ok))
        if bad:
            self.torn_rows += bad
            return out[ok]
        return out

    def contact_rows_since(self, seq: int) -> tuple[list[tuple[np.void, np.ndarray, np.ndarray, np.ndarray, np.ndarray]], int]:
        """Contact-ring rows written after update row ``seq`` (oldest first): a list of ``(header,
        key[n, 3], position_m[n, 3], normal[n, 3], separation_m[n])`` copies and the new ``seq``.
        Rows overwritten before they were read, or being written, are skipped."""
        head = int(self.contact_head[0])
        first = max(seq, head - CONTACT_ROWS + 1)
        out = []
        for k in range(first, head):
            i = k % CONTACT_ROWS
            h = self.contact_hdr[i].copy()
            if int(h["seq"]) != k:
                continue
            n = min(int(h["count"]), MAX_CONTACTS)
            item = (h, self.contact_key[i, :n].copy(), self.contact_position_m[i, :n].copy(),
                    self.contact_normal[i, :n].copy(), self.contact_separation_m[i, :n].copy())
            if int(self.contact_hdr[i]["seq"]) == k:  # not rewritten while copied
                out.append(item)
        return out, head

    def log_transition(self, t_ns: int, from_state: float, to_state: float, reason: int, detail: float) -> None:
        """Append one transition (the loop; the supervisor reads them with ``transitions_since``).
        The row is written before ``status.transitions`` counts it, so a reader never sees a
        counted row half written."""
        st = self.stat[0]
        seq = int(st["transitions"]) + 1
        self.translog[seq % TLOG_ROWS] = (seq, t_ns, int(from_state), int(to_state), int(reason), float(detail))
        st["transitions"] = seq

    def transitions_since(self, seq: int) -> list[tuple]:
        """Transitions logged after ``seq`` (oldest first; at most the last TLOG_ROWS)."""
        last = int(self.stat[0]["transitions"])
        first = max(seq + 1, last - TLOG_ROWS + 1)
        out = []
        for k in range(first, last + 1):
            r = self.translog[k % TLOG_ROWS]
            if int(r["seq"]) == k:
                out.append((k, int(r["t_ns"]), int(r["from_state"]), int(r["to_state"]), int(r["reason"]),
                            float(r["detail"])))
        return out

    def publish_tool(self, seq: int, kind: int, mass_kg: float, com_m, inertia_kg_m2) -> None:
        """The loop, at an engagement (never per step): the engaged tool as its Hello declared it,
        numbered ``seq`` (> 0). ``tool_seq`` is -1 while the fields are written, so a reader that
        copied them meanwhile can tell (``engaged_tool``)."""
        st = self.status
        st[ST["tool_seq"]] = -1.0
        for name, v in zip(_TOOL_FIELDS, (kind, mass_kg, *tuple(com_m)[:3], *tuple(inertia_kg_m2)[:6])):
            st[ST[name]] = float(v)
        st[ST["tool_seq"]] = float(seq)

    def engaged_tool(self) -> tuple[int, int, float, tuple, tuple] | None:
        """The newest engaged tool ``(seq, kind, mass_kg, com_m, inertia_kg_m2)`` (the supervisor),
        or None before the first or while the loop writes one."""
        st = self.status
        seq = st[ST["tool_seq"]]
        got = [float(st[ST[name]]) for name in _TOOL_FIELDS]
        if not seq > 0 or st[ST["tool_seq"]] != seq:
            return None
        return int(seq), int(got[0]), got[1], tuple(got[2:5]), tuple(got[5:11])

    def request(self, name: str) -> int:
        self.control[CT[name]] += 1
        return int(self.control[CT[name]])


def flat_rows(rows: np.ndarray) -> np.ndarray:
    """Structured telemetry rows as float64[n, NTEL] (columns ``TEL``)."""
    return np.ascontiguousarray(rows).view(np.float64).reshape(len(rows), NTEL)


def percentiles(hist: np.ndarray, qs=(0.5, 0.99, 0.999)) -> dict:
    """Percentiles (us, bin upper edges) of a 1-us histogram of any length (its last bin holds
    everything beyond); ``max`` is the highest bin hit."""
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
        out[_qname(q)] = float(min(idx, len(h) - 1) + 1)
    out["max"] = float(np.nonzero(h)[0][-1] + 1)
    return out


def _qname(q: float) -> str:
    s = f"{q * 100:g}".replace(".", "")
    return f"p{s}"
