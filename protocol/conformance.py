"""Protocol v1 conformance kit: ``hapticproxy protocol check-client | check-server``.

``check-client --listen URL`` plays a server on ``URL`` and checks the first client that
connects; ``check-server --connect URL`` plays a client against the server at ``URL``. Each
prints one PASS/FAIL line per rule (see :data:`CLIENT_RULES`, :data:`SERVER_RULES`) and exits 1 if
any rule failed, 2 on a usage or set-up error. ``--hmac-key-file`` enables shared-secret mode
(the key never goes on the command line).

The module also holds the project's reference peers (:func:`run_reference_client`,
:func:`run_reference_server`), small loops over the session endpoints that the tests check
with the kit, and that show how a real peer drives :mod:`hapticproxy.protocol.session`.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import threading
import time
from dataclasses import dataclass, field

import msgpack
import numpy as np

from .codec import Bye, Codec, ContactUpdate, Error, Heartbeat, Hello, ProtocolError, ProxyState, Reject, Welcome
from .messages import PROTOCOL_MAJOR, PROTOCOL_MINOR, ErrorCode, MessageType, ToolKind
from .session import MacFramer, ClientEndpoint, ServerConfig, ServerEndpoint, load_hmac_key
from .transport.base import TransportError

_NS = 1_000_000_000
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])

CLIENT_RULES = {
    "hello-valid": "the first packet is a valid Hello (decodes, units SI, version range includes 1)",
    "hello-retry": "an unanswered Hello is resent with the same client_nonce",
    "session-header": "every packet after Welcome carries the granted session_id and token",
    "fields-valid": "every packet decodes and validates (types, finite values, unit normals, unique keys)",
    "seq": "ContactUpdate.seq starts at 1 and grows by exactly 1 per packet (loopback: no loss)",
    "env-time": "ContactUpdate.env_time_s never decreases",
    "capacity": "no ContactUpdate has more contacts than granted",
    "rate": "ContactUpdates arrive at 1 Hz to the haptic rate, and no silence exceeds 2 heartbeat intervals",
    "bye": "after the server's Bye the client sends nothing more (after a 0.25 s grace)",
}
SERVER_RULES = {
    "reject-major": "a Hello of an unknown major is answered by Reject UNSUPPORTED_VERSION with our nonce",
    "welcome": "a valid Hello gets a Welcome with our nonce, non-zero session id/token, version 1.x, sane grants",
    "ack": "every ContactUpdate is acknowledged by a ProxyState with ack_seq = its seq (loopback, >= 90 %)",
    "proxy-valid": "every ProxyState decodes, carries our session/token, seq strictly increasing, ack_seq never ahead",
    "ack-latency": "median update-to-acknowledgement time <= 20 ms",
    "stale": "a repeated (old) ContactUpdate is not acknowledged",
    "bad-token": "a ContactUpdate with a wrong token is not acknowledged",
    "invalid": "an invalid ContactUpdate (NaN) is not acknowledged and is answered by an Error",
    "heartbeat": "a quiet session gets a Heartbeat within 2 heartbeat intervals",
    "bye": "after our Bye the session is gone: a following ContactUpdate is not acknowledged",
}


@dataclass
class Report:
    rules: dict[str, str]
    results: dict[str, tuple[bool, str]] = field(default_factory=dict)

    def check(self, rule: str, ok: bool, detail: str = "") -> bool:
        if rule not in self.rules:
            raise KeyError(rule)
        if rule in self.results and not self.results[rule][0]:
            return False  # the first failure stays
        self.results[rule] = (bool(ok), detail)
        return bool(ok)

    @property
    def passed(self) -> bool:
        return all(self.results.get(r, (False, ""))[0] for r in self.rules)

    def lines(self) -> list[str]:
        out = []
        for rule, text in self.rules.items():
            ok, detail = self.results.get(rule, (False, "not reached"))
            out.append(f"{'PASS' if ok else 'FAIL'}  {rule:<15} {text}" + (f"  [{detail}]" if detail else ""))
        out.append("RESULT: " + ("PASS" if self.passed else "FAIL"))
        return out


def _contacts(n: int, phase: float):
    keys = np.column_stack([np.zeros(n), np.full(n, 3), np.arange(n)]).astype(np.int64)
    pos = np.column_stack([np.linspace(-0.05, 0.05, n), np.zeros(n), np.zeros(n)])
    nor = np.tile([0.0, 0.0, 1.0], (n, 1))
    return keys, pos, nor, np.full(n, 0.001 * math.sin(phase)), np.zeros(n)


def _open(url: str, role: str):
    from .transport import open_transport  # imported late: keeps `import conformance` light

    return open_transport(url, role=role)


# ------------------------------------------------------------------------- check-client
def check_client(transport, *, duration_s: float = 2.0, hmac_key: bytes | None = None,
                 timeout_s: float = 10.0, config: ServerConfig | None = None) -> Report:
    """Play a server on ``transport`` (role server) and check the first client that connects."""
    rep = Report(CLIENT_RULES)
    cfg = config or ServerConfig(max_contacts=16)
    codec = Codec(cfg.limits)
    mac = MacFramer(hmac_key) if hmac_key else None

    def send(packet: bytes, peer) -> None:
        transport.send(mac.seal(packet) if mac else packet, peer)

    def recv():
        got = transport.recv()
        if got is None:
            return None
        data, peer = got
        if mac is not None:
            data = mac.open(data)
            if data is None:
                rep.check("fields-valid", False, "a datagram with a bad HMAC tag")
                return None
        return data, peer

    deadline = time.monotonic() + timeout_s
    first = None
    while first is None and time.monotonic() < deadline:
        first = recv()
        if first is None:
            time.sleep(0.0005)
    if first is None:
        rep.check("hello-valid", False, f"no packet within {timeout_s} s")
        return rep
    data, peer = first
    hello = codec.try_decode(data)
    ok = (isinstance(hello, Hello) and hello.units == "SI"
          and hello.version_min[0] <= PROTOCOL_MAJOR <= hello.version_max[0])
    rep.check("hello-valid", ok, "" if ok else f"got {hello!r}"[:160])
    if not ok:
        return rep
    # Ignore the first Hello: a conforming client resends it (same nonce).
    retry = None
    t_retry = time.monotonic() + 3.0
    while retry is None and time.monotonic() < t_retry:
        got = recv()
        if got is None:
            time.sleep(0.0005)
            continue
        again = codec.try_decode(got[0])
        if isinstance(again, Hello):
            retry = again
    rep.check("hello-retry", retry is not None and retry.client_nonce == hello.client_nonce,
              "no retry within 3 s" if retry is None else f"nonce {retry.client_nonce:#x} vs {hello.client_nonce:#x}")
    session_id, token = 0x5EC0_0001, 0x7E57_7E57_7E57_7E57
    grant = min(hello.max_contacts, cfg.max_contacts)
    welcome = Welcome(client_nonce=hello.client_nonce, version=(PROTOCOL_MAJOR, min(PROTOCOL_MINOR, hello.version_max[1])),
                      haptic_rate_hz=cfg.haptic_rate_hz, epsilon_m=min(hello.epsilon_m, cfg.max_epsilon_m),
                      max_contacts=grant, heartbeat_interval_s=cfg.heartbeat_interval_s,
                      silence_timeout_s=cfg.silence_timeout_s, server_name="conformance", session_id=session_id, token=token)
    send(codec.encode(welcome), peer)
    arrivals, seqs, times = [], [], []
    last_rx = time.monotonic()
    max_gap = 0.0
    proxy_seq = 0
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        got = recv()
        now = time.monotonic()
        if got is None:
            time.sleep(0.0002)
            continue
        data, p = got
        msg = codec.try_decode(data)
        if isinstance(msg, ProtocolError):
            rep.check("fields-valid", False, str(msg)[:160])
            continue
        if isinstance(msg, Hello):
            if msg.client_nonce == hello.client_nonce:
                send(codec.encode(welcome), peer)  # the Welcome may have crossed a retry
                continue
        max_gap = max(max_gap, now - last_rx)
        last_rx = now
        rep.check("session-header", msg.session_id == session_id and msg.token == token and p == peer,
                  f"{type(msg).__name__} with session {msg.session_id:#x}, token {msg.token:#x}")
        if isinstance(msg, ContactUpdate):
            arrivals.append(now)
            seqs.append(msg.seq)
            times.append(msg.env_time_s)
            rep.check("capacity", msg.n_contacts <= grant, f"{msg.n_contacts} contacts > granted {grant}")
            proxy_seq += 1
            send(codec.encode(ProxyState(seq=proxy_seq, ack_seq=msg.seq, server_time_s=now, proxy_pose=IDENTITY,
                                         proxy_twist=np.zeros(6), wrench=np.zeros(6), session_id=session_id,
                                         token=token)), peer)
    rep.check("fields-valid", True)
    rep.check("session-header", True)
    rep.check("capacity", bool(seqs), "no ContactUpdate received")
    rep.check("seq", bool(seqs) and seqs == list(range(1, len(seqs) + 1)), f"first seqs {seqs[:8]}")
    rep.check("env-time", bool(times) and all(b >= a for a, b in zip(times, times[1:])), "env_time_s went back")
    rate = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0]) if len(arrivals) > 2 else 0.0
    max_gap = max(max_gap, time.monotonic() - last_rx)
    rep.check("rate", 1.0 <= rate <= cfg.haptic_rate_hz and max_gap <= 2 * cfg.heartbeat_interval_s,
              f"{rate:.1f} Hz, longest silence {max_gap * 1000:.0f} ms")
    bye = codec.encode(Bye(code=ErrorCode.BYE_SHUTDOWN, reason="conformance check over", session_id=session_id, token=token))
    for _ in range(3):
        send(bye, peer)
    grace_end = time.monotonic() + 0.25
    while time.monotonic() < grace_end:
        recv()
        time.sleep(0.001)
    late = 0
    quiet_end = time.monotonic() + 0.5
    while time.monotonic() < quiet_end:
        got = recv()
        if got is None:
            time.sleep(0.001)
        else:
            late += 1
    rep.check("bye", late == 0, f"{late} packets after Bye")
    return rep


# ------------------------------------------------------------------------- check-server
class _Probe:
    """A bare client socket: raw packets out, decoded packets in (no session logic, on purpose)."""

    def __init__(self, url: str, mac: MacFramer | None) -> None:
        self.t = _open(url, "client")
        self.mac = mac
        self.codec = Codec()

    def send(self, packet: bytes) -> None:
        self.t.send(self.mac.seal(packet) if self.mac else packet)

    def recv_all(self, wait_s: float) -> list:
        out, end = [], time.monotonic() + wait_s
        while time.monotonic() < end:
            got = self.t.recv()
            if got is None:
                time.sleep(0.0002)
                continue
            data = got[0]
            if self.mac is not None:
                data = self.mac.open(data)
                if data is None:
                    out.append(ProtocolError(ErrorCode.BAD_MAC, "", "bad HMAC tag"))
                    continue
            out.append((time.monotonic(), self.codec.try_decode(data)))
        return out

    def close(self) -> None:
        self.t.close()


def _hello(nonce: int, max_contacts: int = 8) -> Hello:
    return Hello(client_nonce=nonce, engine="hapticproxy-conformance", tool_kind=ToolKind.SPATIAL, mass_kg=1.0,
                 inertia_kg_m2=(0.01, 0.01, 0.01, 0.0, 0.0, 0.0), max_contacts=max_contacts, epsilon_m=0.005,
                 env_rate_hz=60.0)


def check_server(url: str, *, duration_s: float = 1.0, hmac_key: bytes | None = None, rate_hz: float = 60.0) -> Report:
    """Play a client against the server at ``url`` and check it."""
    rep = Report(SERVER_RULES)
    mac = MacFramer(hmac_key) if hmac_key else None
    codec = Codec()
    # 1. Unknown major, from its own socket (another peer), before the real session.
    probe = _Probe(url, mac)
    try:
        obj = msgpack.unpackb(codec.encode(_hello(0xBAD0)))
        obj[0], obj[6], obj[7], obj[8:] = PROTOCOL_MAJOR + 1, [PROTOCOL_MAJOR + 1, 0], [PROTOCOL_MAJOR + 1, 0], ["v+1"]
        probe.send(msgpack.packb(obj))
        got = [m for _, m in (x for x in probe.recv_all(0.5) if isinstance(x, tuple))]
        rej = [m for m in got if isinstance(m, Reject)]
        rep.check("reject-major", bool(rej) and rej[0].code == ErrorCode.UNSUPPORTED_VERSION and rej[0].client_nonce == 0xBAD0,
                  f"got {[type(m).__name__ for m in got]}")
    finally:
        probe.close()
    # 2. The real session.
    probe = _Probe(url, mac)
    try:
        _check_session(probe, rep, duration_s, rate_hz)
    finally:
        probe.close()
    return rep


def _check_session(probe: _Probe, rep: Report, duration_s: float, rate_hz: float) -> None:
    codec = probe.codec
    nonce = 0xC0FFEE
    welcome = None
    for _ in range(8):
        probe.send(codec.encode(_hello(nonce)))
        for _, m in (x for x in probe.recv_all(0.25) if isinstance(x, tuple)):
            if isinstance(m, Welcome) and m.client_nonce == nonce:
                welcome = m
        if welcome:
            break
    ok = (welcome is not None and welcome.session_id != 0 and welcome.token != 0 and welcome.version[0] == PROTOCOL_MAJOR
          and 1 <= welcome.max_contacts <= 8 and 0 <= welcome.epsilon_m <= 0.005 and welcome.haptic_rate_hz > 0)
    rep.check("welcome", ok, "no Welcome" if welcome is None else repr(welcome)[:160])
    if not ok:
        return
    sid, tok, grant = welcome.session_id, welcome.token, welcome.max_contacts
    sent: dict[int, float] = {}
    states: list[tuple[float, ProxyState]] = []
    others: list = []

    def cu(seq: int, token: int = tok, poison: bool = False) -> bytes:
        keys, pos, nor, d, v = _contacts(min(grant, 3), seq * 0.1)
        if poison:
            d = d.copy()
            d[0] = math.nan
        return codec.encode_contact_update(sid, token, seq, seq / rate_hz, IDENTITY, keys, pos, nor, d, v)

    def collect(wait_s: float) -> None:
        for item in probe.recv_all(wait_s):
            if not isinstance(item, tuple):
                rep.check("proxy-valid", False, "bad HMAC tag")
                continue
            t, m = item
            if isinstance(m, ProxyState):
                states.append((t, m))
            else:
                others.append(m)

    seq = 0
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        seq += 1
        sent[seq] = time.monotonic()
        probe.send(cu(seq))
        collect(1.0 / rate_hz)
    collect(0.1)
    acked = {m.ack_seq: t for t, m in states}
    hits = [s for s in sent if s in acked]
    rep.check("ack", len(hits) >= 0.9 * len(sent), f"{len(hits)}/{len(sent)} acknowledged")
    lat = [acked[s] - sent[s] for s in hits]
    med = statistics.median(lat) if lat else math.inf
    rep.check("ack-latency", med <= 0.020, f"median {med * 1000:.2f} ms")
    pseqs = [m.seq for _, m in states]
    bad = [m for _, m in states if m.session_id != sid or m.token != tok or m.ack_seq > seq]
    rep.check("proxy-valid", not bad and all(b > a for a, b in zip(pseqs, pseqs[1:])) and bool(states),
              f"{len(bad)} bad headers/acks, seqs {pseqs[:6]}")
    errs = [m for m in others if isinstance(m, ProtocolError)]
    rep.check("proxy-valid", not errs, str(errs[0])[:160] if errs else "")

    def not_acked(packet: bytes, seq_probe: int, rule: str, what: str) -> list:
        states.clear()
        others.clear()
        probe.send(packet)
        collect(0.15)
        hit = [m for _, m in states if m.ack_seq == seq_probe]
        rep.check(rule, not hit, f"{what} was acknowledged")
        return list(others)

    # A repeat of an older update: neither acknowledged nor allowed to move ack_seq backwards.
    old = max(1, seq - 2)
    states.clear()
    probe.send(cu(old))
    collect(0.15)
    rep.check("stale", seq > 1 and all(m.ack_seq == seq for _, m in states), f"acks after it: {[m.ack_seq for _, m in states]}")
    seq += 1
    not_acked(cu(seq, token=tok ^ 0xFFFF), seq, "bad-token", "an update with a wrong token")
    seq += 1
    replies = not_acked(cu(seq, poison=True), seq, "invalid", "an update with NaN")
    errors = [m for m in replies if isinstance(m, Error)]
    rep.check("invalid", bool(errors) and errors[0].code == ErrorCode.NON_FINITE,
              f"replies {[type(m).__name__ for m in replies]}")
    interval = welcome.heartbeat_interval_s
    others.clear()
    collect(2 * interval + 0.05)
    hbs = [m for m in others if isinstance(m, Heartbeat) and m.session_id == sid and m.token == tok]
    rep.check("heartbeat", bool(hbs), f"no Heartbeat in {2 * interval + 0.05:.2f} s")
    probe.send(codec.encode(Bye(code=ErrorCode.BYE_NORMAL, reason="conformance done", session_id=sid, token=tok)))
    collect(0.05)
    seq += 1
    not_acked(cu(seq), seq, "bye", "an update after Bye")


# ------------------------------------------------------------------------- reference peers
def run_reference_server(transport, stop: threading.Event, *, config: ServerConfig | None = None,
                         hmac_key: bytes | None = None, period_s: float = 0.001) -> ServerEndpoint:
    """The project's reference server loop (a stand-in local model: the proxy sits at the origin).
    Runs until ``stop`` is set; returns the endpoint (for its counters)."""
    server = ServerEndpoint(transport.send, config, hmac_key=hmac_key)
    while not stop.is_set():
        now = time.monotonic_ns()
        for data, peer in transport.drain():
            update = server.receive(data, peer, now)
            if update is not None:
                server.send_proxy_state(update.session_id, now, IDENTITY, np.zeros(6), np.zeros(6))
        server.poll(now)
        time.sleep(period_s)
    server.close_all()
    return server


def run_reference_client(transport, stop: threading.Event, *, rate_hz: float = 60.0, n_contacts: int = 4,
                         hmac_key: bytes | None = None, duration_s: float | None = None) -> ClientEndpoint:
    """The project's reference environment client: a tool resting on a plane with ``n_contacts``
    vertex-face contacts, stepped at ``rate_hz``. Stops on ``stop``, a Bye, or after
    ``duration_s`` (then it sends Bye)."""
    hello = _hello(0, max_contacts=n_contacts)
    client = ClientEndpoint(transport.send, hello, hmac_key=hmac_key)
    client.start()
    step = 0
    t0 = time.monotonic()
    next_step = t0
    while not stop.is_set():
        now = time.monotonic_ns()
        while (got := transport.recv()) is not None:
            client.receive(got[0], got[1], now)
        if client.state in ("rejected", "closed"):
            break
        if duration_s is not None and time.monotonic() - t0 >= duration_s:
            client.close(now_ns=now)
            break
        if time.monotonic() >= next_step:
            if client.established:
                step += 1
                n = min(n_contacts, client.welcome.max_contacts)
                client.send_contacts(now, step / rate_hz, IDENTITY, *_contacts(n, step * 0.1))
            next_step += 1.0 / rate_hz
        client.poll(now)
        time.sleep(0.0005)
    return client


# ------------------------------------------------------------------------------ CLI
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="hapticproxy protocol", description="Protocol v1 conformance kit.")
    sub = parser.add_subparsers(dest="mode", required=True)
    pc = sub.add_parser("check-client", help="play a server and check the client that connects")
    pc.add_argument("--listen", default="udp://127.0.0.1:9870", help="transport URL to listen on")
    pc.add_argument("--duration", type=float, default=2.0, help="seconds of ContactUpdates to observe")
    pc.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the client's Hello")
    ps = sub.add_parser("check-server", help="play a client and check the server")
    ps.add_argument("--connect", default="udp://127.0.0.1:9870", help="transport URL of the server")
    ps.add_argument("--duration", type=float, default=1.0, help="seconds of ContactUpdates to send")
    for p in (pc, ps):
        p.add_argument("--hmac-key-file", default=None,
                       help="file holding the shared secret as hex (mode 600); or set HAPTICPROXY_HMAC_KEY[_FILE]")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0) and 2
    try:
        key = load_hmac_key(args.hmac_key_file)
        if args.mode == "check-client":
            t = _open(args.listen, "server")
            print(f"check-client: listening on {t.url}", flush=True)
            try:
                rep = check_client(t, duration_s=args.duration, hmac_key=key, timeout_s=args.timeout)
            finally:
                t.close()
        else:
            rep = check_server(args.connect, duration_s=args.duration, hmac_key=key)
    except (OSError, ValueError, TransportError) as exc:
        print(f"hapticproxy protocol {args.mode}: {exc}", file=sys.stderr)
        return 2
    print("\n".join(rep.lines()))
    return 0 if rep.passed else 1


if __name__ == "__main__":
    sys.exit(main())
