"""Attacks over UDP on loopback against the real server (supervisor + haptic-loop process) while
a real client holds a session in contact: forged tokens, replayed packets, stale sequence numbers,
a spoofed source (another socket with the session's valid token), a wrong protocol version, and
floods of junk datagrams (20,000 paced ones, 100,000 with ``-m slow``; 100,000 unpaced ones).
Every attack datagram must be rejected and counted by reason, and
the session must not notice: same session, the loop stepping on without a fault, engaged at full
gain, the real client's updates still applied and acknowledged. Counts only, never timings: what
a flood does to the loop's rate (the share of steps kept on time, of the client's updates applied)
is judged on the wall clock, so those tests are marked ``realtime`` (their own step of
``.ci/run``, not the default run).

One server serves the module while it is healthy; a test that failed, or a server that is no
longer engaged with its one session and no fault, is replaced by a fresh one before the next test
(the ``live`` fixture), so one failure does not fail every test after it."""
from __future__ import annotations

import os
import random
import socket
import threading
import time

import msgpack
import numpy as np
import pytest
from server_harness import WallEnv

from hapticproxy.protocol.codec import Codec, ContactUpdate, Hello, Reject
from hapticproxy.protocol.messages import ErrorCode, ToolKind
from hapticproxy.server import config as cfgmod
from hapticproxy.server.clock import MonotonicClock
from hapticproxy.server.daemon import Supervisor
from hapticproxy.server.shm import LS, TEL

CODEC = Codec()
FLOOD = 20_000  # the paced junk flood (100,000 with -m slow)
# the unpaced floods: long enough that the steps they span outnumber a stall of the loaded box by
# far (the ratio of steps kept is what they judge)
UNPACED_FLOOD = 100_000
WAIT_S = 60.0  # bound on waiting for the loop to have read what was sent (not a measurement)


def _port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _kernel_drops(port: int) -> int:
    """Datagrams the kernel dropped at the UDP socket bound to 127.0.0.1:port (/proc/net/udp)."""
    want = f"0100007F:{port:04X}"
    try:
        with open("/proc/net/udp") as f:
            for line in f.readlines()[1:]:
                cols = line.split()
                if cols[1] == want:
                    return int(cols[-1])
    except OSError:
        pass
    return 0


class Live:
    """The server and a 60 Hz wall client pushed onto its floor, in contact."""

    def __init__(self) -> None:
        self.port = _port()
        self.url = f"udp://127.0.0.1:{self.port}"
        self.settings = cfgmod.load({
            "loop": {"rate_hz": 1000.0},
            "transport": {"url": self.url},
            "status": {"address": f"127.0.0.1:{_port()}"},
            # a loaded CI box may stall a loop for tens of ms: the device watchdog is not under test here
            "device": {"driver": "sim", "kind": "planar", "watchdog_s": 0.5,
                       "hand": {"type": "constant", "wrench": [0.0, -0.5, 0.0]}},
            # nor the environment's: the test's own 60 Hz client thread shares a process (and the
            # GIL) with the attacker's loop; on a loaded 2-core CI box the loop once left
            # "engaged" during an attack with no fault and the same session (a fade for an update
            # silence of over 0.1 s, the only transition that fits)
            "safety": {"watchdog_s": 0.5},
            "telemetry": {"ring_s": 60.0},
        })
        self.sup = Supervisor(self.settings)
        self.env = None
        self.captured: list[bytes] = []
        self._stop = threading.Event()
        self._thread = None
        self._lock = threading.Lock()

    def start(self) -> None:
        self.sup.start()
        self.env = WallEnv(self.url, MonotonicClock(), rate_hz=60.0)
        send = self.env.ep._send

        def capturing(data):  # what an on-path observer would record
            self.captured.append(bytes(data))
            return send(data)

        self.env.ep._send = capturing
        self._thread = threading.Thread(target=self._drive, daemon=True)
        self._thread.start()
        self.wait(lambda s: s["updates"] >= 60 and s["contacts"] >= 1)

    def _drive(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                self.env.service()
            time.sleep(0.0005)

    def send_as_client(self, data: bytes) -> None:
        """A datagram from the real client's own socket (an attacker spoofing its address)."""
        with self._lock:
            self.env.tr.send(data)

    def snap(self) -> dict:
        return self.sup.shared.snapshot()

    def wait(self, cond, timeout_s: float = WAIT_S) -> dict:
        t_end = time.monotonic() + timeout_s
        while True:
            s = self.snap()
            if cond(s):
                return s
            if time.monotonic() > t_end:
                raise AssertionError(f"condition not reached; status {s}")
            time.sleep(0.005)

    def session(self) -> tuple[int, int]:
        return self.env.ep.session_id, self.env.ep.token

    def rows_since(self, head0: int) -> np.ndarray:
        head = int(self.sup.shared.head[0])
        n = min(head - head0, self.sup.ring_rows)
        return self.sup.shared.ring[np.arange(head - n, head) % self.sup.ring_rows].copy()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        if self.env is not None:
            self.env.close()
        self.sup.close()


    def healthy(self) -> bool:
        """Still what every test starts from: the loop process alive, engaged at full gain with its
        one session and no fault, the client established, and nothing left in flight (the
        client paused, two publications alike)."""
        if not (self.sup.proc is not None and self.sup.proc.is_alive() and self.env is not None
                and self.env.ep.established and self._thread is not None and self._thread.is_alive()):
            return False
        try:
            self.wait(lambda s: s["loop_state"] == "engaged" and s["gain"] == 1.0, timeout_s=5.0)
        except AssertionError:
            return False
        with self._lock:  # paused well under the environment watchdog (0.5 s)
            s = _settled(self, timeout_s=0.3, required=False)
        return (s is not None and s["loop_state"] == "engaged" and s["gain"] == 1.0 and s["fault"] == 0
                and s["faults_total"] == 0 and s["sessions_opened"] == 1)


_SHARED: dict = {}


@pytest.fixture
def live(request):
    """The module's server, reused while it stays healthy; replaced after a failed test."""
    lv = _SHARED.get("live")
    if lv is not None and not lv.healthy():
        _SHARED.pop("live").close()
        lv = None
    if lv is None:
        lv = Live()
        try:
            lv.start()
        except BaseException:
            lv.close()
            raise
        _SHARED["live"] = lv
    yield lv
    rep = getattr(request.node, "rep_call", None)
    if rep is None or rep.failed:
        _SHARED.pop("live").close()


@pytest.fixture(scope="module", autouse=True)
def _close_the_shared_server():
    yield
    lv = _SHARED.pop("live", None)
    if lv is not None:
        lv.close()


def _attacker() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


def _update(sid: int, token: int, seq: int, depth_m: float = 0.0, n: int = 2) -> bytes:
    """A well-formed ContactUpdate; ``depth_m`` > 0 reports the floor that deep (a yank)."""
    keys = np.array([[0, 1, i] for i in range(n)], dtype=np.int64).reshape(n, 3)
    pos = np.zeros((n, 3))
    nor = np.tile([0.0, 1.0, 0.0], (n, 1))
    sep = np.full(n, -depth_m)
    return CODEC.encode_contact_update(sid, token, seq, 1.0, (0, 0, 0, 1, 0, 0, 0), keys, pos, nor, sep, np.zeros(n))


def _unaffected(live: Live, before: dict, head0: int) -> dict:
    """The session went on as if nothing happened: more real updates applied and acked, same
    session, no fault, engaged at full gain in every step since ``head0``."""
    s = live.wait(lambda s: s["updates"] >= before["updates"] + 10)
    assert s["session_id"] == before["session_id"] and s["sessions_opened"] == before["sessions_opened"] == 1
    assert s["faults_total"] == 0 and s["fault"] == 0
    # every applied update acknowledged: the last perhaps in the step after the snapshot
    assert 0 <= s["updates"] - s["acks_sent"] <= 1
    assert s["steps"] > before["steps"]
    rows = live.rows_since(head0)
    assert len(rows) > 0
    assert np.all(rows[:, TEL["loop_state"]] == LS["engaged"])
    assert np.all(rows[:, TEL["gain"]] == 1.0)
    assert live.env.ep.established
    return s


def _paced(live: Live, sends: list) -> int:
    """Send ``(send_fn, datagram)`` pairs keeping at most 100 unread by the server (the socket
    buffer holds a few hundred; more would be dropped by the kernel, not by us). Returns the
    kernel's drops at the server socket meanwhile (0 expected)."""
    drops0 = _kernel_drops(live.port)
    r0 = live.snap()["datagrams_received"]
    sent = 0
    for fn, pkt in sends:
        while sent - (live.snap()["datagrams_received"] - r0) >= 100:
            time.sleep(0.001)
        fn(pkt)
        sent += 1
    return _kernel_drops(live.port) - drops0


def _delta(a: dict, b: dict, *keys) -> dict:
    return {k: int(b[k] - a[k]) for k in keys}


REASONS = ("decode_errors", "unknown_session", "bad_token", "wrong_peer", "stale_or_duplicate", "unexpected",
           "wrong_version", "rejects_sent", "dropped_packets")


def test_forged_tokens_are_rejected_and_counted(live):
    sid, token = live.session()
    b, head0 = live.snap(), int(live.sup.shared.head[0])
    rng = random.Random(1)
    forged = [t for t in (rng.getrandbits(64) for _ in range(600)) if t != token]
    with _attacker() as atk:
        sends = [(lambda p: atk.sendto(p, ("127.0.0.1", live.port)), _update(sid, t, 10**9 + i, depth_m=0.5)) for i, t in enumerate(forged[:300])]
        # the same from the real client's own address
        sends += [(live.send_as_client, _update(sid, t, 10**9 + i, depth_m=0.5)) for i, t in enumerate(forged[300:])]
        assert _paced(live, sends) == 0
    a = live.wait(lambda s: s["bad_token"] >= b["bad_token"] + len(forged))
    d = _delta(b, a, *REASONS)
    assert d["bad_token"] == len(forged)
    assert d["wrong_peer"] == 0 and d["stale_or_duplicate"] == 0 and d["decode_errors"] == 0
    _unaffected(live, b, head0)


def test_replayed_packets_are_rejected_and_counted(live):
    ours = [p for p in live.captured if isinstance(CODEC.try_decode(p), ContactUpdate)]
    assert len(ours) >= 60
    replay = ours[-200:]
    b, head0 = live.snap(), int(live.sup.shared.head[0])
    with _attacker() as atk:
        sends = [(live.send_as_client, p) for p in replay]  # from the client's address: old seq
        sends += [(lambda p: atk.sendto(p, ("127.0.0.1", live.port)), p) for p in replay]  # from elsewhere
        assert _paced(live, sends) == 0
    a = live.wait(lambda s: s["stale_or_duplicate"] + s["wrong_peer"]
                  >= b["stale_or_duplicate"] + b["wrong_peer"] + 2 * len(replay))
    d = _delta(b, a, *REASONS)
    assert d["stale_or_duplicate"] == len(replay)
    assert d["wrong_peer"] == len(replay)
    assert d["bad_token"] == 0 and d["decode_errors"] == 0
    _unaffected(live, b, head0)


def test_stale_sequence_numbers_with_the_right_token_are_rejected(live):
    sid, token = live.session()
    newest = live.env.ep.contact_seq
    assert newest > 10
    b, head0 = live.snap(), int(live.sup.shared.head[0])
    # valid session and token, from the client's address, old sequence numbers
    assert _paced(live, [(live.send_as_client, _update(sid, token, 1 + i % (newest - 1), depth_m=0.5))
                         for i in range(300)]) == 0
    a = live.wait(lambda s: s["stale_or_duplicate"] >= b["stale_or_duplicate"] + 300)
    d = _delta(b, a, *REASONS)
    assert d["stale_or_duplicate"] == 300 and d["bad_token"] == 0 and d["wrong_peer"] == 0
    _unaffected(live, b, head0)


def test_a_spoofed_source_with_a_valid_token_is_rejected(live):
    sid, token = live.session()
    b, head0 = live.snap(), int(live.sup.shared.head[0])
    f_before = live.rows_since(head0 - 50)[:, TEL["cmd_fy"]]
    with _attacker() as atk:
        # far-future sequence numbers and a floor half a metre deep: accepted, they would yank
        # the user's hand and lock the real client out of its own sequence window
        assert _paced(live, [(lambda p: atk.sendto(p, ("127.0.0.1", live.port)), _update(sid, token, 10**12 + i, depth_m=0.5))
                             for i in range(300)]) == 0
    a = live.wait(lambda s: s["wrong_peer"] >= b["wrong_peer"] + 300)
    d = _delta(b, a, *REASONS)
    assert d["wrong_peer"] == 300 and d["stale_or_duplicate"] == 0
    # the real client's next updates were still applied: waited for explicitly (the attack may
    # outlast the ten updates _unaffected waits for, and then its snapshot can equal ``a``)
    live.wait(lambda s: s["updates"] > a["updates"])
    s = _unaffected(live, b, head0)
    assert s["updates"] > a["updates"]
    fy = live.rows_since(head0)[:, TEL["cmd_fy"]]
    assert np.max(np.abs(fy)) <= np.max(np.abs(f_before)) + 0.05  # no yank reached the hand


def test_a_wrong_protocol_version_is_refused_and_counted(live):
    sid, token = live.session()
    b, head0 = live.snap(), int(live.sup.shared.head[0])
    hello = Hello(client_nonce=7, engine="from the future", tool_kind=ToolKind.PLANAR, mass_kg=0.2,
                  inertia_kg_m2=(2e-4, 2e-4, 2e-4, 0, 0, 0), max_contacts=8, epsilon_m=0.005, env_rate_hz=60.0,
                  version_min=(2, 0), version_max=(2, 3))
    v2_hello = CODEC.encode(hello)
    obj = msgpack.unpackb(v2_hello)
    obj[0] = 2  # and the envelope of a major-2 speaker
    v2_envelope = msgpack.packb(obj, use_bin_type=True)
    obj = msgpack.unpackb(_update(sid, token, 10**12))
    obj[0] = 2
    v2_update = msgpack.packb(obj, use_bin_type=True)
    rejects = []
    with _attacker() as atk:
        atk.settimeout(5.0)
        for pkt in (v2_hello, v2_envelope):
            atk.sendto(pkt, ("127.0.0.1", live.port))
            rejects.append(CODEC.try_decode(atk.recv(2048)))
    assert _paced(live, [(live.send_as_client, v2_update)] * 50) == 0
    a = live.wait(lambda s: s["wrong_version"] >= b["wrong_version"] + 51 and s["rejects_sent"] >= b["rejects_sent"] + 2)
    d = _delta(b, a, *REASONS)
    assert all(isinstance(r, Reject) and r.code == ErrorCode.UNSUPPORTED_VERSION for r in rejects)
    assert d["rejects_sent"] == 2
    assert d["wrong_version"] == 51  # the major-2 envelopes: one Hello, 50 updates
    assert d["decode_errors"] == 51
    assert a["sessions_opened"] == 1
    _unaffected(live, b, head0)


def _junk(rng: np.random.Generator, sid: int, token: int, real: bytes) -> list[bytes]:
    """One round of 10 junk datagrams of five kinds (none of them a Hello)."""
    out = []
    for _ in range(2):
        out.append(b"\xc1" + rng.bytes(int(rng.integers(0, 200))))  # never valid msgpack
        cut = int(rng.integers(1, len(real)))
        out.append(real[:cut])  # a truncated real packet
    for _ in range(2):
        out.append(_update(int(rng.integers(1, 2**32)) or 1, int(rng.integers(1, 2**63)), 1))  # unknown session
        out.append(_update(sid, (token + 1 + int(rng.integers(0, 2**40))) % 2**64 or 1, 1))  # forged token
    out.append(real)  # a replay from elsewhere
    out.append(real)
    return out


def _junk_flood(live: Live, flood: int) -> dict:
    """``flood`` junk datagrams, paced; every one read and refused for its reason. Returns the
    counts the tests judge."""
    sid, token = live.session()
    real = [p for p in live.captured if isinstance(CODEC.try_decode(p), ContactUpdate)][-1]
    rng = np.random.default_rng(8)
    pool = []
    while len(pool) < 2000:
        pool.extend(_junk(rng, sid, token, real))
    kinds_sent = flood
    b, head0 = live.snap(), int(live.sup.shared.head[0])
    env_sent0 = live.env.ep.counters.sent
    drops0 = _kernel_drops(live.port)
    rejected = ("decode_errors", "unknown_session", "bad_token", "wrong_peer")

    def rejected_since(s):
        return sum(s[k] - b[k] for k in rejected)

    sent = 0
    with _attacker() as atk:
        dst = ("127.0.0.1", live.port)
        while sent < flood:
            # keep at most ~300 in flight: the loop reads 32 per step, the socket buffer holds
            # a few hundred; beyond that the kernel would drop them (checked below)
            s = live.snap()
            room = int(300 - (sent - rejected_since(s)))
            for _ in range(max(0, min(room, flood - sent))):
                atk.sendto(pool[sent % len(pool)], dst)
                sent += 1
            if room <= 0:
                time.sleep(0.001)
        drops = _kernel_drops(live.port) - drops0
        a = live.wait(lambda s: rejected_since(s) + drops >= kinds_sent)
    env_sent = live.env.ep.counters.sent - env_sent0
    d = _delta(b, a, *REASONS, "datagrams_received", "updates", "acks_sent", "steps", "missed_deadlines")
    # every junk datagram was read and refused for a reason (or dropped by the kernel, counted there)
    assert drops == 0, f"the kernel dropped {drops} datagrams: the pacing let the socket buffer overflow"
    assert rejected_since(a) == flood
    assert d["datagrams_received"] >= flood
    assert d["decode_errors"] == flood // 10 * 4
    assert d["unknown_session"] == flood // 10 * 2
    assert d["bad_token"] == flood // 10 * 2
    assert d["wrong_peer"] == flood // 10 * 2
    assert d["stale_or_duplicate"] == 0 and d["rejects_sent"] == 0
    # the session did not notice: the real client's updates applied all along, no fault, engaged
    # at full gain in every step
    s = _unaffected(live, b, head0)
    assert d["updates"] > 0
    stepped = s["steps"] - b["steps"]
    missed = s["missed_deadlines"] - b["missed_deadlines"]
    print(f"flood: {flood} junk datagrams, {d['steps']} steps, {missed} missed deadlines, "
          f"{d['updates']} updates applied of {env_sent} client datagrams, kernel drops {drops}, pid {os.getpid()}")
    return dict(updates=d["updates"], env_sent=env_sent, stepped=stepped, missed=missed)


@pytest.mark.parametrize("flood", [FLOOD, pytest.param(100_000, marks=pytest.mark.slow)])
def test_a_flood_of_junk_is_rejected_and_counted_and_the_session_goes_on(live, flood):
    _junk_flood(live, flood)


@pytest.mark.realtime
def test_a_flood_of_junk_does_not_slow_the_loop(live):
    """The same flood, judged on the wall clock: the loop kept its rate (periods skipped are few)
    and read the real client's updates as they came (newest-wins merges only a few)."""
    r = _junk_flood(live, FLOOD)
    assert r["updates"] >= 0.9 * (r["env_sent"] - 10)  # heartbeats are not updates
    assert r["stepped"] / (r["stepped"] + r["missed"]) >= 0.9, r


def _settled(live: Live, timeout_s: float = WAIT_S, required: bool = True) -> dict | None:
    """Status once the loop has read everything sent so far (two publications alike); if that did
    not happen within ``timeout_s``: an AssertionError (``required``), else None."""
    prev = None
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        time.sleep(0.03)
        s = live.snap()
        key = (s["datagrams_received"], s["dropped_empty"], s["dropped_packets"])
        if key == prev:
            return s
        prev = key
    if required:
        raise AssertionError(f"the server did not settle within {timeout_s} s; status {live.snap()}")
    return None


def test_an_unpaced_flood_is_counted_by_the_server_or_the_kernel_and_no_promise_breaks(live):
    """100,000 datagrams as fast as one process can send them: random junk, empty datagrams and
    oversize ones. The socket buffer overflows, so the kernel drops most (and counts them in
    /proc/net/udp); the server counts the rest by reason. The real client's datagrams compete for
    the same buffer, so the session may lose updates for a while: then the watchdog fades the
    force, as it should. No fault, no step over the rate limit, the session survives."""
    from hapticproxy.benchmarks.bench_faults import analyse, limits_from

    rng = np.random.default_rng(9)
    pool = [b"\xc1" + rng.bytes(int(rng.integers(0, 200))) for _ in range(800)] + [b""] * 100 + [b"o" * 9000] * 100
    rng.shuffle(pool)
    refused = ("decode_errors", "bad_mac", "unknown_session", "bad_token", "wrong_peer", "stale_or_duplicate",
               "unexpected")

    def arrived(s, b):
        """Datagrams the server read since ``b``: to the session layer, empty, or oversize."""
        oversize = (s["dropped_packets"] - b["dropped_packets"]) - sum(s[k] - b[k] for k in refused)
        return (s["datagrams_received"] - b["datagrams_received"]) + (s["dropped_empty"] - b["dropped_empty"]) + oversize

    with live._lock:  # the client pauses (< the watchdog) so that the books balance exactly
        b = _settled(live)
        env0 = live.env.ep.counters.sent
        drops0 = _kernel_drops(live.port)
    head0 = int(live.sup.shared.head[0])
    sent = 0
    with _attacker() as atk:
        atk.setblocking(False)
        dst = ("127.0.0.1", live.port)
        for i in range(UNPACED_FLOOD):
            try:
                atk.sendto(pool[i % len(pool)], dst)
                sent += 1
            except BlockingIOError:  # our own send buffer full: not sent
                pass
    with live._lock:
        a = _settled(live)
        env_sent = live.env.ep.counters.sent - env0
        drops = _kernel_drops(live.port) - drops0
    assert sent >= 0.9 * UNPACED_FLOOD
    # every datagram sent to the server was read and refused by it or dropped (and counted) by
    # the kernel; the real client's datagrams are in both books, refused ones are junk only
    assert arrived(a, b) + drops == sent + env_sent
    assert a["dropped_empty"] > b["dropped_empty"] and a["decode_errors"] > b["decode_errors"]
    assert sum(a[k] - b[k] for k in ("unknown_session", "bad_token", "wrong_peer", "stale_or_duplicate")) == 0
    # the session survived, no fault; whatever the lost updates did, every promise held
    s = live.wait(lambda s: s["updates"] >= a["updates"] + 10 and s["loop_state"] == "engaged" and s["gain"] == 1.0)
    assert s["session_id"] == b["session_id"] and s["sessions_opened"] == 1 and s["faults_total"] == 0
    rows = live.rows_since(head0)
    res = analyse(rows, limits_from(live.settings, s), {})
    assert res["violations"] == 0, res["broken"]
    print(f"unpaced flood: sent {sent}, read by the server {int(arrived(a, b))}, "
          f"kernel dropped {drops} (client datagrams sent meanwhile {env_sent}), fades {res['fades']}, "
          f"max step {res['max_force_step_n']:.3f} N")


def _hellos() -> list[bytes]:
    return [CODEC.encode(Hello(client_nonce=i + 1, engine="flood", tool_kind=ToolKind.PLANAR, mass_kg=0.2,
                               inertia_kg_m2=(2e-4, 2e-4, 2e-4, 0, 0, 0), max_contacts=8, epsilon_m=0.005,
                               env_rate_hz=60.0)) for i in range(500)]


def _slow_to_refuse_flood(live: Live, kind: str) -> dict:
    """Datagrams that are slow to refuse: 1 kB msgpack packets of 1,000 nested arrays (~40 us
    each to unpack, ten times other junk), or valid Hellos while the one session slot is taken
    (each decoded, then refused SERVER_FULL before any model check), unpaced. Every one is read
    and refused or dropped by the kernel; the session survives. Returns the counts judged."""
    pool = [b"\x91" * 1023 + b"\x01"] if kind == "nested arrays" else _hellos()
    with live._lock:
        b = _settled(live)
        env0 = live.env.ep.counters.sent
        drops0 = _kernel_drops(live.port)
    sent = 0
    with _attacker() as atk:
        atk.setblocking(False)
        for i in range(UNPACED_FLOOD if kind == "nested arrays" else UNPACED_FLOOD // 5):
            try:
                atk.sendto(pool[i % len(pool)], ("127.0.0.1", live.port))
                sent += 1
            except BlockingIOError:
                pass
    with live._lock:
        a = _settled(live)
        env_sent = live.env.ep.counters.sent - env0
        drops = _kernel_drops(live.port) - drops0
    # read by the server (all refused as malformed) or dropped by the kernel; the real client's
    # datagrams are in both books
    assert (a["datagrams_received"] - b["datagrams_received"]) + drops == sent + env_sent
    refused = "decode_errors" if kind == "nested arrays" else "rejects_sent"
    assert 0 < a[refused] - b[refused] <= sent
    assert a["sessions_opened"] == 1
    stepped = a["steps"] - b["steps"]
    missed = a["missed_deadlines"] - b["missed_deadlines"]
    s = live.wait(lambda s: s["updates"] >= a["updates"] + 10 and s["loop_state"] == "engaged" and s["gain"] == 1.0)
    assert s["session_id"] == b["session_id"] and s["faults_total"] == 0
    cuts = int(a["poll_budget_cuts"] - b["poll_budget_cuts"])
    print(f"{kind} flood: sent {sent}, read by the server {int(a['datagrams_received'] - b['datagrams_received'])}, "
          f"kernel dropped {drops}, {stepped} steps, {int(missed)} missed deadlines, {cuts} polls cut at the budget")
    return dict(stepped=stepped, missed=missed, cuts=cuts)


@pytest.mark.parametrize("kind", ["nested arrays", "valid hellos"])
def test_a_flood_of_datagrams_slow_to_refuse_is_refused_and_the_session_goes_on(live, kind):
    _slow_to_refuse_flood(live, kind)


@pytest.mark.realtime
@pytest.mark.parametrize("kind", ["nested arrays", "valid hellos"])
def test_a_flood_of_datagrams_slow_to_refuse_does_not_stretch_the_steps(live, kind):
    """Read 32 per step, nested arrays stretched steps to milliseconds. The poll's time budget
    leaves the rest for the next step: the loop keeps its rate (the share of steps on time, on the
    wall clock)."""
    r = _slow_to_refuse_flood(live, kind)
    assert r["cuts"] > 0  # the budget did the bounding
    # Unbounded, 32 refusals of ~40 us per step take over a period: every step misses a
    # deadline, so at most half are kept (<= 0.5). Bounded, the loop kept 0.86 (491 of 573) on a
    # 2-core CI box where the unpaced sender itself holds a core; 0.75 separates the two.
    assert r["stepped"] / (r["stepped"] + r["missed"]) >= 0.75, r
