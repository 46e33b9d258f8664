"""The conformance kit: the project's reference peers pass it over every transport (UDP and
Zenoh on 127.0.0.1, free ports; the in-memory bus); the real server passes ``check-server``;
peers broken on purpose fail exactly the rules they break; the command line. Threads,
transports and the server are stopped and closed at the end of each test. (The shipped engine
clients are run against ``check-client`` by tests/clients/test_cli.py; the Box2D example by
tests/examples/.)"""
from __future__ import annotations

import itertools
import os
import socket
import sys
import threading
import time
import types

import msgpack
import numpy as np
import pytest

from hapticproxy.protocol import conformance as K
from hapticproxy.protocol.codec import Bye, Codec, ContactUpdate, Heartbeat, Hello, ProxyState, Reject, Welcome
from hapticproxy.protocol.messages import ErrorCode, ServerState, ToolKind
from hapticproxy.protocol.session import ServerConfig
from hapticproxy.protocol.transport import TransportError, open_transport

KEY = bytes(range(7, 39))
TRANSPORTS = ["udp", "mem", "zenoh"]
_names = itertools.count(1)
#: the reference server with a short silence timeout: check-server waits two of them
FAST_SERVER = ServerConfig(silence_timeout_s=0.5)


def listen_url(kind: str) -> str:
    """A URL to open a server on: loopback, free port (picked by the backend) or a fresh bus name."""
    if kind == "udp":
        return "udp://127.0.0.1:0"
    if kind == "mem":
        return f"mem://conformance-{os.getpid()}-{next(_names)}"
    return f"zenoh://127.0.0.1:0/conformance{next(_names)}"


class Peer:
    """Run fn(transport, stop, **kw) in a thread; stop and join on exit."""

    def __init__(self, fn, transport, **kw):
        self.stop = threading.Event()
        self.result = None
        self.transport = transport

        def run():
            self.result = fn(transport, self.stop, **kw)

        self.thread = threading.Thread(target=run, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(10)
        alive = self.thread.is_alive()
        self.transport.close()
        assert not alive


def failed(rep) -> set[str]:
    return set(rep.failed)


def run_check_client(kind: str, client_fn, key=None, **kw):
    listen = open_transport(listen_url(kind), role="server")
    try:
        with Peer(client_fn, open_transport(listen.url, role="client"), hmac_key=key, **kw):
            return K.check_client(listen, duration_s=0.3, hmac_key=key, timeout_s=10.0)
    finally:
        listen.close()


# --------------------------------------------------------------------------- the report
def test_report_lines_say_why_only_when_failing():
    rep = K.Report({"a": "rule a", "b": "rule b", "c": "rule c"})
    rep.check("a", True, "this text is never shown")
    rep.check("b", False, "it broke")
    rep.check("b", True)  # a later pass never hides a failure
    lines = rep.lines()
    assert lines[0] == "PASS  a  rule a"
    assert lines[1] == "FAIL  b  rule b: it broke"
    assert lines[2] == "FAIL  c  rule c: not reached"
    assert lines[3] == "RESULT: FAIL (2 of 3 rules: b, c)"
    assert not rep.passed
    done = K.Report({"a": "rule a"})
    done.check("a", True)
    assert done.passed and done.lines()[-1] == "RESULT: PASS (1 rules)"
    assert (done.exit_code, rep.exit_code) == (0, 1)
    rep.inconclusive.append("the checker stalled")
    assert rep.lines()[-1] == "RESULT: INCONCLUSIVE (the checker stalled)" and rep.exit_code == 3
    assert not rep.passed and rep.lines()[1] == "FAIL  b  rule b: it broke"  # the rules still say what happened
    done.inconclusive.append("the checker stalled")
    assert done.passed and done.exit_code == 0  # a pass stands, stall or not


def check_server(url: str, **kw) -> K.Report:
    """check-server, once more if the first run was inconclusive: the checker measured that it
    itself (this test process, on a busy machine) sent nothing for the server's silence timeout
    and the server rightly ended the session (seen in CI: a 0.6 s stall of pytest's process)."""
    rep = K.check_server(url, **kw)
    return K.check_server(url, **kw) if rep.inconclusive else rep


def _stall_checker_once(monkeypatch, seconds: float) -> None:
    """The scripted client stops sending for ``seconds`` before its refusal scenario, as when
    its process is stopped by the OS (the server's thread runs on)."""
    original = K._ScriptedClient._refusals

    def stalled(self):
        time.sleep(seconds)
        original(self)

    monkeypatch.setattr(K._ScriptedClient, "_refusals", stalled)


# ------------------------------------------------------------------- reference peers pass
# (the in-memory bus carries the broken peers below; the transports' own contract suite covers it)
# plain UDP is what tests/clients/test_cli.py (every engine's client) and the real server below
# are judged over already: here it is a slow extra
@pytest.mark.parametrize("kind,key", [pytest.param("udp", None, marks=pytest.mark.slow), ("udp", KEY), ("zenoh", KEY)],
                         ids=["udp", "udp-hmac", "zenoh-hmac"])
def test_reference_client_passes_check_client(kind, key):
    rep = run_check_client(kind, K.run_reference_client, key, reconnect_delay_s=0.3)
    assert rep.passed, "\n".join(rep.lines())
    assert all(line.startswith("PASS") for line in rep.lines()[:-1])


# plain UDP is what tests/clients/test_cli.py (every engine's client) and the real server below
# are judged over already: here it is a slow extra
@pytest.mark.parametrize("kind,key", [pytest.param("udp", None, marks=pytest.mark.slow), ("udp", KEY), ("zenoh", KEY)],
                         ids=["udp", "udp-hmac", "zenoh-hmac"])
def test_reference_server_passes_check_server(kind, key):
    srv = open_transport(listen_url(kind), role="server")
    with Peer(K.run_reference_server, srv, hmac_key=key, config=FAST_SERVER, proxy_start="first-update"):
        rep = check_server(srv.url, duration_s=0.5, hmac_key=key)
    assert rep.passed, "\n".join(rep.lines())


def test_a_checker_that_stalls_itself_is_inconclusive_not_a_verdict(monkeypatch):
    """The checker silent for longer than the silence timeout (0.5 s): the reference server
    rightly ends the session with Bye 61; the rules that follow fail, and the report says they
    are the checker's doing (exit 3), not the server's (exit 1)."""
    _stall_checker_once(monkeypatch, 0.8)
    srv = open_transport(listen_url("udp"), role="server")
    with Peer(K.run_reference_server, srv, config=FAST_SERVER, proxy_start="first-update"):
        rep = K.check_server(srv.url, duration_s=0.3)
    bad = failed(rep)
    assert {"bad-address", "invalid", "heartbeat"} <= bad <= set(K._MAIN_SESSION_RULES), "\n".join(rep.lines())
    assert rep.exit_code == 3 and len(rep.inconclusive) == 1, "\n".join(rep.lines())
    last = rep.lines()[-1]
    assert last.startswith("RESULT: INCONCLUSIVE (this checker sent nothing for 0.") and "BYE_TIMEOUT" in last
    assert float(last.split("nothing for ")[1].split(" s")[0]) >= 0.8


def test_a_stall_of_the_checker_excuses_nothing_the_server_did_wrong(monkeypatch):
    """The same stall against a server that never ends a session (nor sends a Bye): its
    failures stay failures."""
    _stall_checker_once(monkeypatch, 0.8)
    srv = open_transport(listen_url("udp"), role="server")
    with Peer(naive_server, srv):
        rep = K.check_server(srv.url, duration_s=0.3)
    assert {"stale", "bad-address", "invalid", "heartbeat"} <= failed(rep), "\n".join(rep.lines())
    assert not rep.inconclusive and rep.exit_code == 1, "\n".join(rep.lines())



# ------------------------------------------------------------------------ the real server
def _free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("device", [pytest.param("planar", marks=pytest.mark.slow), "spatial"])
def test_the_real_server_passes_check_server(device):
    """The daemon (supervisor + loop process) on UDP loopback, as `hapticproxy serve` runs it."""
    from hapticproxy.server import config as cfgmod
    from hapticproxy.server.daemon import Supervisor

    url = f"udp://127.0.0.1:{_free_port()}"
    settings = cfgmod.load({"loop": {"rate_hz": 1000.0, "realtime": False}, "transport": {"url": url},
                            "status": {"address": f"127.0.0.1:{_free_port()}"},
                            "device": {"driver": "sim", "kind": device}})
    sup = Supervisor(settings)
    stop = threading.Event()
    serving = threading.Thread(target=lambda: [sup._serve_status(0.05) for _ in iter(stop.is_set, True)], daemon=True)
    try:
        sup.start()
        serving.start()
        rep = check_server(url, duration_s=1.0)
        snap = sup.shared.snapshot()
    finally:
        stop.set()
        if serving.is_alive():
            serving.join(5)
        sup.close()
    assert rep.passed, "\n".join(rep.lines())
    # nothing the kit sent faulted the server (a stall of the loop process on a loaded machine
    # trips the device watchdog and recovers by itself: counted, but not the kit's doing)
    assert snap["model_nonfinite"] == 0 and snap["device_fault"] == 0
    assert snap["faults_total"] == snap["stall_trips"]


# ----------------------------------------------------------------- clients broken on purpose
def _normalized(q):
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q)
    return q / n if n > 0 else np.array([1.0, 0.0, 0.0, 0.0])


def flawed_client(transport, stop, *, flaws=frozenset(), hmac_key=None, rate_hz=60.0):
    """The reference client's box over the floor, on raw packets, with the listed flaws:

    - ``no-retry``: one Hello, never resent;
    - ``lenient``: reads ProxyStates with plain msgpack (no validation, any token or major) and
      applies the last one that arrived, whatever its seq or server_state; never sends Error;
    - ``xyzw``: reads the proxy's quaternion in x y z w order;
    - ``fixed-timeout``: ends a session after 1 s of silence, whatever Welcome granted;
    - ``ignore-bye``: keeps sending in a session for 1 s after the server's Bye;
    - ``hello-flood``: after a Reject, a new Hello every 0.1 s;
    - ``bad-normal``: every 20th update has a normal of length 2;
    - ``pause``: after its 30th update of the first session, sends nothing for 0.3 s.
    """
    assert hmac_key is None
    codec = Codec()
    hello = K._hello(0, ToolKind.SPATIAL, max_contacts=4)
    pose = K._REF_START.copy()
    sess = None  # (session_id, token, welcome)
    newest = 0
    seq = 0
    last_rx = time.monotonic()
    next_step = next_hello = time.monotonic()
    bye_at = reconnect_at = None
    hellos_sent = 0
    rejected = False

    def send_hello(new: bool):
        """A new Hello (a new nonce), or a retry of the last one (none with no-retry)."""
        nonlocal next_hello, hellos_sent, hello_packet
        if new:
            hello.client_nonce = 0x1000 + hellos_sent + (time.monotonic_ns() % 1000) * 1_000_000
            hello_packet = codec.encode(hello)
        elif "no-retry" in flaws:
            return
        transport.send(hello_packet)
        hellos_sent += 1
        next_hello = time.monotonic() + (0.1 if rejected else 0.25)

    hello_packet = b""
    send_hello(True)
    while not stop.is_set():
        now = time.monotonic()
        while (got := transport.recv()) is not None:
            data = got[0]
            if "lenient" in flaws and sess is not None:
                try:
                    obj = msgpack.unpackb(data)
                except Exception:  # noqa: BLE001
                    continue
                if isinstance(obj, list) and len(obj) > 10 and obj[2] == 5 and isinstance(obj[8], bytes) \
                        and len(obj[8]) == 56:
                    p = np.frombuffer(obj[8], "<f8").copy()
                    p[3:] = _normalized(p[3:])
                    if np.all(np.isfinite(p)):
                        pose = p
                        last_rx = now
                    continue
            m = codec.try_decode(data)
            if isinstance(m, Welcome) and sess is None and m.client_nonce == hello.client_nonce:
                sess = (m.session_id, m.token, m)
                newest = 0
                seq = 0
                last_rx = now
            elif isinstance(m, Reject) and m.client_nonce == hello.client_nonce:
                rejected = True
            elif sess is not None and not isinstance(m, Exception) and (m.session_id, m.token) == sess[:2]:
                if isinstance(m, ProxyState):
                    if m.seq > newest:
                        newest = m.seq
                        last_rx = now
                        if m.server_state in (ServerState.UNKNOWN, ServerState.ENGAGED):
                            pose = np.array(m.proxy_pose)
                            if "xyzw" in flaws:
                                pose[3:] = pose[[4, 5, 6, 3]]
                elif isinstance(m, Heartbeat):
                    last_rx = now
                elif isinstance(m, Bye):
                    if "ignore-bye" in flaws:
                        bye_at = now
                    else:
                        sess = None
                        reconnect_at = now + 0.3
        if rejected:
            if "hello-flood" in flaws and now >= next_hello:
                send_hello(True)
            time.sleep(0.002)
            continue
        if bye_at is not None and now - bye_at > 1.0:
            sess, bye_at, reconnect_at = None, None, now
        if sess is None:
            if reconnect_at is not None and now >= reconnect_at:
                reconnect_at = None
                send_hello(True)
            elif reconnect_at is None and now >= next_hello:
                send_hello(False)
            time.sleep(0.002)
            continue
        timeout = 1.0 if "fixed-timeout" in flaws else sess[2].silence_timeout_s
        if now - last_rx >= timeout and bye_at is None:
            bye = codec.encode(Bye(code=ErrorCode.BYE_TIMEOUT, reason="silent", session_id=sess[0], token=sess[1]))
            for _ in range(3):
                transport.send(bye)
            sess = None
            reconnect_at = now + 0.3
            continue
        if now >= next_step:
            if "pause" in flaws and seq == 30 and hellos_sent <= 2:
                time.sleep(0.3)
                now = time.monotonic()
            seq += 1
            keys, pos, nor, d, v = K._reference_contacts(pose, 4, sess[2].epsilon_m)
            if "bad-normal" in flaws and seq % 20 == 0 and len(nor):
                nor = nor * 2.0
            transport.send(codec.encode_contact_update(sess[0], sess[1], seq, seq / rate_hz, pose, keys, pos, nor, d, v))
            next_step = now + 1.0 / rate_hz
        time.sleep(0.0005)


def test_a_careless_client_fails_the_rules_it_breaks():
    """No Hello retry; every ProxyState datagram applied as it comes (no seq, token, validity or
    server_state check), no Error ever sent."""
    rep = run_check_client("udp", flawed_client, flaws={"no-retry", "lenient"})
    bad = failed(rep)
    broken = {"hello-retry", "proxy-stale", "proxy-duplicate", "proxy-reordered", "proxy-address", "proxy-invalid",
              "error-reply", "server-state", "device-inputs"}
    assert bad == broken, "\n".join(rep.lines())


def test_a_stubborn_client_fails_the_rules_it_breaks():
    """The quaternion read as x y z w, a hard-coded 1 s timeout, the server's Bye ignored for
    1 s, new Hellos every 0.1 s after a Reject, a long normal now and then, a 0.3 s pause."""
    rep = run_check_client("udp", flawed_client, flaws={"xyzw", "fixed-timeout", "ignore-bye", "hello-flood",
                                                         "bad-normal", "pause"})
    bad = failed(rep)
    assert {"initial-pose", "silence-timeout", "bye", "reject", "fields-valid", "rate"} <= bad, "\n".join(rep.lines())
    line = next(ln for ln in rep.lines() if ln.startswith("FAIL  rate"))
    assert float(line.split("longest gap between ContactUpdates ")[1].split(" ms")[0]) >= 300
    # what it does right is still judged right
    assert {"hello-valid", "hello-retry", "follow", "proxy-stale", "proxy-address", "server-state",
            "heartbeats-only"}.isdisjoint(bad), "\n".join(rep.lines())
    line = next(ln for ln in rep.lines() if ln.startswith("FAIL  initial-pose"))
    assert "turned 180.0 deg" in line


def test_a_gap_the_checker_itself_caused_is_not_the_clients():
    """Datagrams that queued while the checker was descheduled are stamped on its wake-up: the
    gap is judged net of the checker's own stalls, and the excuse is reported."""
    srv = K._ScriptedServer.__new__(K._ScriptedServer)
    srv.rep = K.Report(K.CLIENT_RULES)
    srv.cfg = K.ServerConfig()  # haptic_rate_hz bounds the rate
    sess = K._Session.__new__(K._Session)
    ts = [i * 0.01 for i in range(100)] + [1.15 + i * 0.01 for i in range(100)]  # one 160 ms gap
    sess.updates = [(t, None) for t in ts]
    sess.ended = None
    srv.sessions = [sess]
    srv.own_stalls = [(1.0, 1.13)]  # the checker slept 130 ms of it
    srv._final_rules()
    assert srv.rep.ok("rate"), srv.rep.lines()
    srv.rep = K.Report(K.CLIENT_RULES)
    srv.own_stalls = [(1.0, 1.04)]  # 40 ms of it: 120 ms remain the client's
    srv._final_rules()
    ok, why = srv.rep.results["rate"]
    assert not ok
    assert "longest gap between ContactUpdates 120 ms" in why and "net of 40 ms the checker itself" in why, why


def test_a_client_that_never_follows_is_not_judged_on_what_follows_from_following():
    def deaf(transport, stop, **kw):
        # the reference client, but its tool never moves: every ProxyState is dropped
        class Deaf:
            def __init__(self, t):
                self.t = t

            def send(self, data, peer=None):
                return self.t.send(data, peer)

            def recv(self):
                while (got := self.t.recv()) is not None:
                    if Codec().try_decode(got[0]).__class__ is not ProxyState:
                        return got
                return None

            def close(self):
                self.t.close()

        return K.run_reference_client(Deaf(transport), stop, reconnect_delay_s=0.3, **kw)

    rep = run_check_client("mem", deaf)
    bad = failed(rep)
    assert "follow" in bad
    for rule in ("proxy-stale", "server-state", "error-reply"):
        assert rule in bad
        assert "not judged: the tool does not follow the proxy" in dict(
            (r, w) for r, (ok, w) in rep.results.items())[rule]


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_check_client_cli_fails_when_nobody_connects(kind, capsys):
    assert K.main(["check-client", "--listen", listen_url(kind), "--timeout", "0.2"]) == 1
    out = capsys.readouterr().out
    assert "FAIL  hello-valid" in out and "no Hello within 0.2 s" in out and "RESULT: FAIL" in out


# ----------------------------------------------------------------- servers broken on purpose
def naive_server(transport, stop):
    """Acknowledges every ContactUpdate it can decode, whatever its token or seq, with the proxy
    at the origin; version 1.0; never sends Reject, Error, Heartbeat; ignores Bye."""
    codec = Codec(minor=0)
    seq = 0
    while not stop.is_set():
        got = transport.recv()
        if got is None:
            time.sleep(0.0005)
            continue
        data, peer = got
        m = Codec().try_decode(data)
        if isinstance(m, Hello):
            transport.send(codec.encode(Welcome(client_nonce=m.client_nonce, version=(1, 0), haptic_rate_hz=1000.0,
                                                epsilon_m=0.0, max_contacts=m.max_contacts, heartbeat_interval_s=0.05,
                                                silence_timeout_s=1.0, session_id=1, token=2)), peer)
        elif isinstance(m, ContactUpdate):
            seq += 1
            transport.send(codec.encode(ProxyState(seq=seq, ack_seq=m.seq, server_time_s=0.0, proxy_pose=K.IDENTITY,
                                                   proxy_twist=np.zeros(6), wrench=np.zeros(6), session_id=1,
                                                   token=2)), peer)


@pytest.mark.parametrize("kind", ["udp", pytest.param("mem", marks=pytest.mark.slow)])
def test_a_naive_server_fails_the_rules_it_breaks(kind):
    srv = open_transport(listen_url(kind), role="server")
    with Peer(naive_server, srv):
        rep = K.check_server(srv.url, duration_s=0.3)
    bad = failed(rep)
    assert {"reject-major", "reject-units", "reject-hello", "welcome-note", "initial-pose", "server-state", "stale",
            "bad-address", "invalid", "capacity", "out-of-bounds", "unusable", "seq-jump", "heartbeat", "bye",
            "silence"} <= bad, "\n".join(rep.lines())
    assert {"welcome", "hello-repeat", "ack", "ack-latency", "proxy-valid"}.isdisjoint(bad), "\n".join(rep.lines())


def test_a_server_whose_proxy_starts_at_the_origin_fails_initial_pose_only():
    srv = open_transport(listen_url("udp"), role="server")
    with Peer(K.run_reference_server, srv, config=FAST_SERVER, proxy_start="origin"):
        rep = K.check_server(srv.url, duration_s=0.3)
    assert failed(rep) == {"initial-pose"}, "\n".join(rep.lines())
    line = next(ln for ln in rep.lines() if ln.startswith("FAIL"))
    assert "mm and" in line and "from the first tool_pose" in line


def test_a_server_that_uses_up_refused_seqs_fails_the_refusal_rules(monkeypatch):
    """The reference server, except that an update refused for its content (scene bounds,
    unusable contacts) still uses up its seq, so that seq can never be sent again."""
    from hapticproxy.protocol import session as S

    original = S.ServerSession.check_update

    def check_after_seq(self, msg):
        why = original(self, msg)
        if why is not None and msg.seq > self.contact_seq.newest:
            self.contact_seq.newest = msg.seq
        return why

    monkeypatch.setattr(S.ServerSession, "check_update", check_after_seq)
    srv = open_transport(listen_url("mem"), role="server")
    with Peer(K.run_reference_server, srv, config=FAST_SERVER, proxy_start="first-update"):
        rep = K.check_server(srv.url, duration_s=0.3)
    bad = failed(rep)
    assert {"out-of-bounds", "unusable"} <= bad, "\n".join(rep.lines())
    assert "the same seq, valid, was not acknowledged afterwards" in rep.results["out-of-bounds"][1]
    assert {"invalid", "capacity", "welcome", "ack", "stale"}.isdisjoint(bad), "\n".join(rep.lines())


# ------------------------------------------------------------------------------ the CLI
def test_cli_usage_errors(capsys):
    assert K.main(["check-server", "--connect", "not-a-url"]) == 2
    assert K.main(["bogus"]) == 2
    assert K.main(["check-client", "--direction", "1,2"]) == 2
    assert K.main(["check-client", "--step", "0.5", "--listen", "udp://127.0.0.1:0", "--timeout", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "step_m" in err


def test_check_device_dispatches_to_the_device_kit(monkeypatch, capsys):
    seen = []
    fake = types.ModuleType("hapticproxy.protocol.device_conformance")
    fake.main = lambda argv: seen.append(list(argv)) or 7
    monkeypatch.setitem(sys.modules, "hapticproxy.protocol.device_conformance", fake)
    assert K.main(["check-device", "--connect", "udp://127.0.0.1:9872", "--x"]) == 7
    assert seen == [["--connect", "udp://127.0.0.1:9872", "--x"]]


def test_check_device_without_the_device_kit_says_so(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "hapticproxy.protocol.device_conformance", None)
    assert K.main(["check-device"]) == 2
    err = capsys.readouterr().err
    assert "check-device" in err and "hapticproxy.protocol.device_conformance" in err and "Traceback" not in err


def free_tcp_port() -> int:
    return _free_port(socket.SOCK_STREAM)


def test_cli_check_server_over_zenoh_url(capsys):
    # The command line, end to end, on an explicit zenoh://127.0.0.1:PORT/SESSION URL.
    srv = open_transport(f"zenoh://127.0.0.1:{free_tcp_port()}/cli-server", role="server")
    with Peer(K.run_reference_server, srv, config=FAST_SERVER, proxy_start="first-update"):
        assert K.main(["check-server", "--connect", srv.url, "--duration", "0.3"]) == 0
    out = capsys.readouterr().out
    assert out.strip().endswith(f"RESULT: PASS ({len(K.SERVER_RULES)} rules)")


@pytest.mark.slow
def test_cli_check_server_over_zenoh_url_exits_1_for_a_failing_server():
    with Peer(naive_server, open_transport(f"zenoh://127.0.0.1:{free_tcp_port()}/cli-naive", role="server")) as p:
        assert K.main(["check-server", "--connect", p.transport.url, "--duration", "0.3"]) == 1


def test_cli_check_client_over_zenoh_url(capsys):
    # check-client listens on the URL given; the reference client connects once it is up.
    url = f"zenoh://127.0.0.1:{free_tcp_port()}/cli-client"
    result = {}
    cli = threading.Thread(target=lambda: result.setdefault(
        "rc", K.main(["check-client", "--listen", url, "--duration", "0.3", "--timeout", "20"])), daemon=True)
    cli.start()
    client = None
    deadline = time.monotonic() + 20
    while client is None:
        try:
            client = open_transport(url, role="client", connect_timeout_s=0.5)
        except TransportError:  # the listener is not up yet
            assert time.monotonic() < deadline and cli.is_alive(), "check-client never listened"
            time.sleep(0.05)
    with Peer(K.run_reference_client, client, reconnect_delay_s=0.3):
        cli.join(60)
    assert not cli.is_alive()
    out = capsys.readouterr().out
    assert result.get("rc") == 0, out
    assert f"listening on {url}" in out and f"RESULT: PASS ({len(K.CLIENT_RULES)} rules)" in out
    assert all(ln.startswith(("PASS", "RESULT", "check-client")) for ln in out.strip().splitlines())
