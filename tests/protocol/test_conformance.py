"""The conformance kit against the project's reference peers (must pass) and deliberately broken
peers (must fail the rules they break), over every transport: UDP and Zenoh on 127.0.0.1 (free
ports: port 0 for UDP, a free port the Zenoh backend picks), and the in-memory bus. Threads and
transports are stopped and closed at the end of each test."""
from __future__ import annotations

import itertools
import math
import os
import socket
import threading
import time

import numpy as np
import pytest

from hapticproxy.protocol import conformance as K
from hapticproxy.protocol.codec import Codec, ContactUpdate, Hello, ProxyState, Welcome
from hapticproxy.protocol.messages import ToolKind
from hapticproxy.protocol.transport import TransportError, open_transport

KEY = bytes(range(7, 39))
TRANSPORTS = ["udp", "mem", "zenoh"]
_names = itertools.count(1)


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
        assert not self.thread.is_alive()
        self.transport.close()


def failed(rep):
    return {r for r, (ok, _) in rep.results.items() if not ok} | {r for r in rep.rules if r not in rep.results}


@pytest.mark.parametrize("key", [None, KEY], ids=["plain", "hmac"])
@pytest.mark.parametrize("kind", TRANSPORTS)
def test_reference_client_passes_check_client(kind, key):
    listen = open_transport(listen_url(kind), role="server")
    try:
        with Peer(K.run_reference_client, open_transport(listen.url, role="client"), hmac_key=key):
            rep = K.check_client(listen, duration_s=0.8, hmac_key=key)
    finally:
        listen.close()
    assert rep.passed, "\n".join(rep.lines())


@pytest.mark.parametrize("key", [None, KEY], ids=["plain", "hmac"])
@pytest.mark.parametrize("kind", TRANSPORTS)
def test_reference_server_passes_check_server(kind, key):
    srv = open_transport(listen_url(kind), role="server")
    with Peer(K.run_reference_server, srv, hmac_key=key):
        rep = K.check_server(srv.url, duration_s=0.5, hmac_key=key)
    assert rep.passed, "\n".join(rep.lines())


def broken_client(transport, stop, *, nan=False):
    """Sends one Hello (never retries), then ContactUpdates that all carry seq 1, and ignores Bye."""
    codec = Codec()
    hello = Hello(client_nonce=77, engine="broken", tool_kind=ToolKind.SPATIAL, mass_kg=1.0,
                  inertia_kg_m2=(0.1, 0.1, 0.1, 0, 0, 0), max_contacts=4)
    transport.send(codec.encode(hello))
    welcome = None
    while not stop.is_set():
        got = transport.recv()
        if got is not None:
            m = codec.try_decode(got[0])
            if isinstance(m, Welcome):
                welcome = m
        if welcome is not None:
            keys, pos, nor, d, v = K._contacts(2, 0.0)
            pkt = codec.encode_contact_update(welcome.session_id, welcome.token, 1, 0.0, K.IDENTITY, keys, pos, nor, d, v)
            if nan:
                import msgpack
                obj = msgpack.unpackb(pkt)
                data = np.frombuffer(obj[10], "<f8").copy()
                data[0] = math.nan
                obj[10] = data.tobytes()
                pkt = msgpack.packb(obj)
            transport.send(pkt)
        time.sleep(0.01)


# Each case waits out check-client's 3 s Hello-retry window, so the NaN-free variant (which only
# drops the fields-valid failure) runs on UDP alone.
@pytest.mark.parametrize("kind,nan", [("udp", False), ("udp", True), ("mem", True), ("zenoh", True)])
def test_broken_client_fails_check_client(kind, nan):
    listen = open_transport(listen_url(kind), role="server")
    try:
        with Peer(broken_client, open_transport(listen.url, role="client"), nan=nan):
            rep = K.check_client(listen, duration_s=0.5)
    finally:
        listen.close()
    bad = failed(rep)
    assert {"hello-retry", "seq", "bye"} <= bad, "\n".join(rep.lines())
    assert ("fields-valid" in bad) == nan


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_check_client_cli_fails_when_nobody_connects(kind):
    assert K.main(["check-client", "--listen", listen_url(kind), "--timeout", "0.2"]) == 1


def naive_server(transport, stop):
    """Acknowledges every ContactUpdate it can decode, whatever its token or seq; never sends
    Reject, Error, Heartbeat; ignores Bye."""
    codec = Codec()
    seq = 0
    while not stop.is_set():
        got = transport.recv()
        if got is None:
            time.sleep(0.0005)
            continue
        data, peer = got
        m = codec.try_decode(data)
        if isinstance(m, Hello):
            transport.send(codec.encode(Welcome(client_nonce=m.client_nonce, version=(1, 0), haptic_rate_hz=1000.0,
                                                epsilon_m=0.0, max_contacts=m.max_contacts, heartbeat_interval_s=0.05,
                                                silence_timeout_s=1.0, session_id=1, token=2)), peer)
        elif isinstance(m, ContactUpdate):
            seq += 1
            transport.send(codec.encode(ProxyState(seq=seq, ack_seq=m.seq, server_time_s=0.0, proxy_pose=K.IDENTITY,
                                                   proxy_twist=np.zeros(6), wrench=np.zeros(6), session_id=1,
                                                   token=2)), peer)


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_broken_server_fails_check_server(kind):
    srv = open_transport(listen_url(kind), role="server")
    with Peer(naive_server, srv):
        rep = K.check_server(srv.url, duration_s=0.3)
    bad = failed(rep)
    assert {"reject-major", "stale", "bad-token", "invalid", "heartbeat", "bye"} <= bad, "\n".join(rep.lines())
    assert {"welcome", "ack", "ack-latency"}.isdisjoint(bad), "\n".join(rep.lines())


def test_cli_usage_errors():
    assert K.main(["check-server", "--connect", "not-a-url"]) == 2
    assert K.main(["bogus"]) == 2


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_cli_check_server_over_zenoh_url():
    # The command line, end to end, on an explicit zenoh://127.0.0.1:PORT/SESSION URL.
    srv = open_transport(f"zenoh://127.0.0.1:{free_tcp_port()}/cli-server", role="server")
    with Peer(K.run_reference_server, srv):
        assert K.main(["check-server", "--connect", srv.url, "--duration", "0.3"]) == 0
    with Peer(naive_server, open_transport(f"zenoh://127.0.0.1:{free_tcp_port()}/cli-naive", role="server")) as p:
        assert K.main(["check-server", "--connect", p.transport.url, "--duration", "0.3"]) == 1


def test_cli_check_client_over_zenoh_url(capsys):
    # check-client listens on the URL given; the reference client connects once it is up.
    url = f"zenoh://127.0.0.1:{free_tcp_port()}/cli-client"
    result = {}
    cli = threading.Thread(target=lambda: result.setdefault(
        "rc", K.main(["check-client", "--listen", url, "--duration", "0.8", "--timeout", "20"])), daemon=True)
    cli.start()
    client = None
    deadline = time.monotonic() + 20
    while client is None:
        try:
            client = open_transport(url, role="client", connect_timeout_s=0.5)
        except TransportError:  # the listener is not up yet
            assert time.monotonic() < deadline and cli.is_alive(), "check-client never listened"
            time.sleep(0.05)
    with Peer(K.run_reference_client, client):
        cli.join(30)
    assert not cli.is_alive()
    out = capsys.readouterr().out
    assert result.get("rc") == 0, out
    assert f"listening on {url}" in out and "RESULT: PASS" in out
