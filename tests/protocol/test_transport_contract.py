"""One contract, three backends: every test here runs against mem, udp and zenoh.

Asynchronous backends are waited on with ``_recv_wait`` whose deadline only guards against a
hang (a lost packet fails the test at the deadline); no assertion depends on how fast anything
is. Sockets and Zenoh endpoints bind 127.0.0.1 on ports picked free, and everything opened is
closed by the ``net`` fixture.
"""
from __future__ import annotations

import itertools
import os
import random
import sys
import threading
import time

import pytest

from hapticproxy.protocol.transport import (
    MemTransport,
    Transport,
    TransportClosedError,
    TransportError,
    open_transport,
    parse_transport_url,
)

BACKENDS = ("mem", "udp", "zenoh")
HANG_GUARD_S = 10.0  # a packet that has not arrived by then is lost: the test fails
# Largest back-to-back burst each backend is specified to carry without loss on loopback: mem's
# queue and UDP's socket buffer hold hundreds; Zenoh's REAL_TIME TX queue holds 16 datagrams,
# beyond which its congestion control may drop (see zenoh_backend.TX_QUEUE_REAL_TIME_BATCHES).
BURST = {"mem": 200, "udp": 200, "zenoh": 16}
_names = itertools.count(1)


class Net:
    """Opens servers/clients of one backend and closes all of them at teardown."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.opened: list[Transport] = []

    def server(self, **options) -> Transport:
        if self.kind == "mem":
            url = f"mem://contract-{os.getpid()}-{next(_names)}"
        elif self.kind == "udp":
            url = "udp://127.0.0.1:0"
        else:
            url = f"zenoh://127.0.0.1:0/contract{next(_names)}"
        t = open_transport(url, role="server", **options)
        self.opened.append(t)
        return t

    def client(self, server: Transport, **options) -> Transport:
        t = open_transport(server.url, role="client", **options)
        self.opened.append(t)
        return t

    def close_all(self) -> None:
        for t in reversed(self.opened):
            t.close()


@pytest.fixture(params=BACKENDS)
def net(request):
    n = Net(request.param)
    yield n
    n.close_all()
    for t in n.opened:
        assert t.closed


def _recv_wait(t: Transport, timeout_s: float = HANG_GUARD_S):
    deadline = time.monotonic() + timeout_s
    while True:
        item = t.recv()
        if item is not None:
            return item
        if time.monotonic() > deadline:
            return None
        time.sleep(0.0002)


def _recv_n(t: Transport, n: int, timeout_s: float = HANG_GUARD_S) -> list:
    out = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() <= deadline:
        item = t.recv()
        if item is None:
            time.sleep(0.0002)
            continue
        out.append(item)
    return out


def _connected(net: Net, **client_options):
    """A server and a client whose first exchange completed (so the server knows its peer id)."""
    server = net.server()
    client = net.client(server, **client_options)
    assert client.send(b"hello")
    got = _recv_wait(server)
    assert got is not None and got[0] == b"hello"
    return server, client, got[1]


# ---------------------------------------------------------------------------- both ways


def test_send_and_receive_both_ways(net):
    server, client, peer = _connected(net)
    assert server.send(b"ack-1", peer)
    assert _recv_wait(client) == (b"ack-1", client.default_peer)
    assert client.send(b"update-2")
    assert _recv_wait(server) == (b"update-2", peer)
    # A client may name its one peer explicitly.
    assert client.send(b"update-3", client.default_peer)
    assert _recv_wait(server) == (b"update-3", peer)
    assert server.counters.received == 3 and server.counters.sent == 1
    assert client.counters.sent == 3 and client.counters.received == 1
    assert server.counters.bytes_received == len(b"hello") + len(b"update-2") + len(b"update-3")


def test_payloads_are_byte_exact(net):
    server, client, peer = _connected(net)
    rng = random.Random(1234)
    payloads = [
        bytes(range(256)),
        b"\x00",
        b"\x00" * 17,
        bytes([0xC1]) * 3,  # msgpack's never-used byte: the transport must not care
        rng.randbytes(1300),  # a 32-contact ContactUpdate
        rng.randbytes(200),  # a ProxyState acknowledgement
        rng.randbytes(server.max_packet_bytes),  # exactly at the limit
    ]
    for p in payloads:
        assert client.send(p)
        assert _recv_wait(server) == (p, peer)
        assert server.send(p, peer)
        assert _recv_wait(client) == (p, client.default_peer)
    # bytearray and memoryview payloads carry the same bytes.
    assert client.send(bytearray(b"ba"))
    assert _recv_wait(server) == (b"ba", peer)
    assert client.send(memoryview(b"xxmvxx")[2:4])
    assert _recv_wait(server) == (b"mv", peer)


def test_recv_into_uses_caller_buffer_and_reports_peer(net):
    server, client, peer = _connected(net)
    buf = bytearray(server.max_packet_bytes)
    view = memoryview(buf)
    assert client.send(b"into-me")
    deadline = time.monotonic() + HANG_GUARD_S
    while (res := server.recv_into(view))[1] is None and time.monotonic() < deadline:
        time.sleep(0.0002)
    assert res == (7, peer)
    assert bytes(buf[:7]) == b"into-me"
    with pytest.raises(ValueError, match="max_packet_bytes"):
        server.recv_into(bytearray(server.max_packet_bytes - 1))


def test_empty_receive_returns_at_once(net):
    server, client, peer = _connected(net)
    buf = bytearray(server.max_packet_bytes)
    results = []

    def poll() -> None:
        # Nothing is ever sent during this loop: a blocking receive would never come back.
        for _ in range(2000):
            results.append(server.recv_into(buf))
            results.append(client.recv_into(buf))
        results.append(server.recv())
        results.append(client.recv())
        results.append(server.drain_into(buf))
        results.append(server.drain())

    worker = threading.Thread(target=poll, daemon=True)
    worker.start()
    worker.join(HANG_GUARD_S)
    assert not worker.is_alive(), "receive blocked with nothing waiting"
    assert results[:4000] == [(0, None)] * 4000
    assert results[4000:] == [None, None, (0, None, 0), []]
    assert server.counters.received == 1  # only the hello


def test_empty_payload_is_refused(net):
    server, client, peer = _connected(net)
    with pytest.raises(ValueError, match="empty"):
        client.send(b"")
    with pytest.raises(ValueError, match="empty"):
        server.send(b"", peer)
    assert client.counters.sent == 1


# ---------------------------------------------------------------------------- size limit


def test_oversize_send_is_refused_and_counted(net):
    server, client, peer = _connected(net)
    too_big = b"x" * (client.max_packet_bytes + 1)
    assert client.send(too_big) is False
    assert server.send(too_big, peer) is False
    assert client.counters.dropped_oversize_send == 1
    assert server.counters.dropped_oversize_send == 1
    assert client.counters.dropped_oversize == 1
    # Nothing of it went out: the next datagram each side sees is the marker.
    assert client.send(b"marker-c")
    assert server.send(b"marker-s", peer)
    assert _recv_wait(server) == (b"marker-c", peer)
    assert _recv_wait(client) == (b"marker-s", client.default_peer)
    assert client.counters.sent == 2 and server.counters.sent == 1


def test_oversize_arrival_is_dropped_and_counted(net):
    # The client may send up to 4096 bytes, the server accepts at most 1024.
    server = net.server(max_packet_bytes=1024)
    client = net.client(server, max_packet_bytes=4096)
    assert client.send(b"x" * 1025)
    assert client.send(b"y" * 4096)
    assert client.send(b"z" * 1024)
    got = _recv_wait(server)
    assert got is not None and got[0] == b"z" * 1024
    assert server.counters.dropped_oversize_recv == 2
    assert server.counters.received == 1
    # And the other way round: the server's limit is below what the client would accept.
    assert server.send(b"w" * 1024, got[1])
    assert _recv_wait(client) == (b"w" * 1024, client.default_peer)


def test_drain_into_keeps_the_newest_valid_datagram_past_an_oversize_one(net):
    server = net.server(max_packet_bytes=1024)
    client = net.client(server, max_packet_bytes=4096)
    assert client.send(b"keep-me")
    assert client.send(b"\xee" * 2000)  # arrives after, and must not clobber the newest
    buf = bytearray(b"\x00" * 1024)
    valid = 0
    deadline = time.monotonic() + HANG_GUARD_S
    while (valid < 1 or server.counters.dropped_oversize_recv < 1) and time.monotonic() < deadline:
        nbytes, peer, count = server.drain_into(buf)
        if count:
            valid += count
            last = (nbytes, peer)
        else:
            time.sleep(0.0002)
    assert valid == 1 and server.counters.dropped_oversize_recv == 1
    assert last[0] == 7 and bytes(buf[:7]) == b"keep-me" and buf[7] == 0


@pytest.mark.parametrize("bad", [0, -1, 65508, "big"])
def test_bad_max_packet_bytes_is_a_value_error(net, bad):
    with pytest.raises(ValueError, match="max_packet_bytes"):
        net.server(max_packet_bytes=bad)


# ---------------------------------------------------------------------------- lifecycle


def test_close_is_idempotent_and_use_after_close_raises(net):
    server, client, peer = _connected(net)
    client.close()
    client.close()
    assert client.closed
    with pytest.raises(TransportClosedError):
        client.send(b"late")
    with pytest.raises(TransportClosedError):
        client.recv()
    server.close()
    server.close()
    with pytest.raises(TransportClosedError):
        server.recv_into(bytearray(server.max_packet_bytes))


def test_context_manager_closes(net):
    server = net.server()
    with net.client(server) as client:
        assert client.send(b"ctx")
        assert _recv_wait(server)[0] == b"ctx"
    assert client.closed
    with server:
        pass
    assert server.closed


def test_server_send_needs_a_peer(net):
    server, client, peer = _connected(net)
    with pytest.raises(ValueError, match="peer"):
        server.send(b"to whom?")


# ---------------------------------------------------------------------------- peers


def test_replies_reach_the_right_peer_among_two_clients(net):
    server = net.server()
    a = net.client(server)
    b = net.client(server)
    assert a.send(b"from-a")
    assert b.send(b"from-b")
    got = dict((data, peer) for data, peer in _recv_n(server, 2))
    assert set(got) == {b"from-a", b"from-b"}
    peer_a, peer_b = got[b"from-a"], got[b"from-b"]
    assert peer_a != peer_b
    hash(peer_a), hash(peer_b)  # peer ids are hashable (dict keys in the session layer)
    # Reply in the opposite order of arrival; each client gets only its own reply.
    assert server.send(b"to-b", peer_b)
    assert server.send(b"to-a", peer_a)
    assert _recv_wait(a) == (b"to-a", a.default_peer)
    assert _recv_wait(b) == (b"to-b", b.default_peer)
    # Peer ids are stable: the next datagram from a carries the same id.
    assert a.send(b"again-a")
    assert _recv_wait(server) == (b"again-a", peer_a)
    assert a.recv() is None and b.recv() is None


def test_drain_keeps_newest_per_peer(net):
    server = net.server()
    a = net.client(server)
    b = net.client(server)
    n_a = min(20, BURST[net.kind])
    for i in range(n_a):
        assert a.send(b"a%02d" % i)
    for i in range(5):
        assert b.send(b"b%02d" % i)
    total = n_a + 5
    # Collect every datagram, whatever drains it takes to arrive, keeping the per-peer newest.
    newest: dict = {}
    total_returned = 0
    deadline = time.monotonic() + HANG_GUARD_S
    while total_returned + server.counters.superseded < total and time.monotonic() < deadline:
        batch = server.drain(newest_per_peer=True)
        assert len({peer for _, peer in batch}) == len(batch)  # at most one per peer per drain
        for data, peer in batch:
            newest[peer] = data
        total_returned += len(batch)
        if not batch:
            time.sleep(0.0002)
    assert server.counters.received == total
    assert total_returned + server.counters.superseded == total
    assert sorted(newest.values()) == [b"a%02d" % (n_a - 1), b"b04"]


def test_many_packets_drained_newest_wins(net):
    server, client, peer = _connected(net)
    n_packets = BURST[net.kind]
    for i in range(n_packets):
        assert server.send(b"ack-%04d" % i + b"." * 190, peer)
    buf = bytearray(client.max_packet_bytes)
    reads = 0
    last = b""
    drains_with_data = 0
    deadline = time.monotonic() + HANG_GUARD_S
    while reads < n_packets and time.monotonic() < deadline:
        nbytes, src, count = client.drain_into(buf)
        if count:
            assert src == client.default_peer
            reads += count
            drains_with_data += 1
            last = bytes(buf[:nbytes])
        else:
            time.sleep(0.0002)
    assert reads == n_packets
    assert last.startswith(b"ack-%04d" % (n_packets - 1))
    assert client.counters.superseded == n_packets - drains_with_data
    assert client.counters.received == n_packets


def test_drain_all_keeps_arrival_order_and_bounds_one_call(net):
    server, client, peer = _connected(net)
    n_packets = min(30, BURST[net.kind])
    for i in range(n_packets):
        assert client.send(b"u%02d" % i)
    got = []
    deadline = time.monotonic() + HANG_GUARD_S
    while len(got) < n_packets and time.monotonic() < deadline:
        batch = server.drain(max_packets=7)
        assert len(batch) <= 7
        got.extend(batch)
        if not batch:
            time.sleep(0.0002)
    # Loopback UDP, a Zenoh TCP link and the mem queue all keep order for one sender.
    assert [d for d, _ in got] == [b"u%02d" % i for i in range(n_packets)]
    assert {p for _, p in got} == {peer}
    assert server.counters.superseded == 0
    with pytest.raises(ValueError, match="max_packets"):
        server.drain(max_packets=0)


# ---------------------------------------------------------------------------- factory


def test_factory_accepts_mapping_and_keyword_options(net):
    server = net.server(max_packet_bytes=2000)
    assert server.max_packet_bytes == 2000
    client = open_transport({"url": server.url, "max_packet_bytes": 3000}, role="client")
    net.opened.append(client)
    assert client.max_packet_bytes == 3000
    other = open_transport({"url": server.url, "max_packet_bytes": 3000}, role="client", max_packet_bytes=1500)
    net.opened.append(other)
    assert other.max_packet_bytes == 1500


def test_factory_rejects_unknown_options(net):
    server = net.server()
    with pytest.raises(ValueError, match="'no_such_option'"):
        open_transport(server.url, role="client", no_such_option=1)
    with pytest.raises(ValueError, match="role"):
        open_transport(server.url, role="listener")


@pytest.mark.parametrize(
    "url, match",
    [
        ("tcp://127.0.0.1:1", "scheme"),
        ("127.0.0.1:9000", "scheme://"),
        ("udp://127.0.0.1", "HOST:PORT"),
        ("udp://127.0.0.1:99999", "host:port"),
        ("udp://127.0.0.1:9000/path", "no path"),
        ("mem://", "name"),
        ("udp://127.0.0.1:9000?rcvbuf_bytes=1&rcvbuf_bytes=2", "twice"),
        ("udp://127.0.0.1:9000?rcvbuf_bytes=lots", "rcvbuf_bytes"),
    ],
)
def test_bad_urls_are_value_errors(url, match):
    with pytest.raises(ValueError, match=match):
        open_transport(url, role="client")


def test_parse_transport_url():
    assert parse_transport_url("udp://127.0.0.1:9000").port == 9000
    u = parse_transport_url("zenoh://127.0.0.1:7447/lab?mode=client&ring_capacity=8")
    assert (u.scheme, u.host, u.port, u.name) == ("zenoh", "127.0.0.1", 7447, "lab")
    assert u.options == {"mode": "client", "ring_capacity": "8"}
    assert parse_transport_url("udp://[::1]:9000").host == "::1"
    assert parse_transport_url("mem://bus-1").name == "bus-1"


# ---------------------------------------------------------------------------- backend specifics


def test_mem_queue_overflow_evicts_oldest_and_counts():
    server, client = MemTransport.pair(queue_capacity=4)
    try:
        for i in range(10):
            assert client.send(b"%d" % i)
        assert server.counters.dropped_overflow == 6
        assert [d for d, _ in server.drain()] == [b"6", b"7", b"8", b"9"]
    finally:
        client.close()
        server.close()


def test_mem_name_rules():
    server, client = MemTransport.pair()
    try:
        with pytest.raises(TransportError, match="already has a server"):
            MemTransport(server.name, "server")
        with pytest.raises(TransportError, match="no mem server"):
            MemTransport("nobody-here", "client")
        # A client of a closed server counts its sends as errors instead of raising.
        server.close()
        assert client.send(b"x") is False
        assert client.counters.send_errors == 1
    finally:
        client.close()
        server.close()


def test_server_send_to_unknown_peer_counts_an_error_mem_and_zenoh():
    for kind in ("mem", "zenoh"):
        n = Net(kind)
        try:
            server, client, peer = _connected(n)
            assert server.send(b"who?", "not-a-peer-id") is False
            assert server.counters.send_errors == 1
        finally:
            n.close_all()


def test_udp_client_of_absent_server_counts_errors_and_never_raises():
    # Bind then close a socket: its port is (for a moment) certainly not served.
    probe = open_transport("udp://127.0.0.1:0", role="server")
    url = probe.url
    probe.close()
    with open_transport(url, role="client") as client:
        for _ in range(5):
            client.send(b"anyone?")
            client.recv()
        # Loopback returns ICMP port-unreachable, surfaced as errors on later calls.
        assert client.counters.send_errors + client.counters.recv_errors >= 1
        assert client.counters.received == 0


def test_udp_exposes_bound_address_and_socket_buffers():
    with open_transport("udp://127.0.0.1:0?rcvbuf_bytes=65536&sndbuf_bytes=65536", role="server") as server:
        host, port = server.local_address
        assert host == "127.0.0.1" and port > 0
        assert server.url == f"udp://127.0.0.1:{port}"
        assert server.rcvbuf_bytes_granted >= 65536 // 2
        with open_transport(server.url, role="client", rcvbuf_bytes=0) as client:
            assert client.default_peer == ("127.0.0.1", port)
            assert client.url == server.url


def _raw_zenoh(listen: str | None = None, connect: str | None = None):
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    cfg.insert_json5("listen/endpoints", f'["{listen}"]' if listen else "[]")
    cfg.insert_json5("connect/endpoints", f'["{connect}"]' if connect else "[]")
    return zenoh.open(cfg)


def _try_recv_wait(sub):
    deadline = time.monotonic() + HANG_GUARD_S
    while (sample := sub.try_recv()) is None and time.monotonic() < deadline:
        time.sleep(0.0002)
    return sample


def test_zenoh_wire_format_is_the_documented_keys_and_raw_bytes():
    """Plain Zenoh sessions that know only the documented key expressions interoperate."""
    import zenoh

    from hapticproxy.protocol.transport.zenoh_backend import c2s_key, s2c_key

    payload = bytes(range(256)) * 3
    # 1. A raw Zenoh "server" and our client.
    probe = open_transport("udp://127.0.0.1:0", role="server")  # borrow a free port number
    port = probe.local_address[1]
    probe.close()
    raw_server = _raw_zenoh(listen=f"tcp/127.0.0.1:{port}")
    try:
        sub = raw_server.declare_subscriber("hapticproxy/wire/c2s/*", zenoh.handlers.RingChannel(8))
        with open_transport(f"zenoh://127.0.0.1:{port}/wire", role="client") as client:
            assert client.send(payload)
            sample = _try_recv_wait(sub)
            assert sample is not None
            assert str(sample.key_expr) == c2s_key("wire", client.client_id)
            assert sample.payload.to_bytes() == payload
            pub = raw_server.declare_publisher(s2c_key("wire", client.client_id))
            deadline = time.monotonic() + HANG_GUARD_S
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.001)
            pub.put(payload[::-1])
            assert _recv_wait(client) == (payload[::-1], client.default_peer)
            pub.undeclare()
        sub.undeclare()
    finally:
        raw_server.close()
    # 2. Our server and a raw Zenoh "client" with a made-up id.
    n = Net("zenoh")
    try:
        server = n.server()
        raw_client = _raw_zenoh(connect=server.endpoint)
        try:
            my_id = "0123abcd"
            sub = raw_client.declare_subscriber(s2c_key(server.session_name, my_id), zenoh.handlers.RingChannel(8))
            pub = raw_client.declare_publisher(c2s_key(server.session_name, my_id))
            deadline = time.monotonic() + HANG_GUARD_S
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.001)
            pub.put(payload)
            assert _recv_wait(server) == (payload, my_id)
            assert server.send(b"ack", my_id)
            sample = _try_recv_wait(sub)
            assert sample is not None and sample.payload.to_bytes() == b"ack"
        finally:
            raw_client.close()
    finally:
        n.close_all()


def test_zenoh_client_without_server_fails_clearly():
    probe = open_transport("udp://127.0.0.1:0", role="server")  # borrow a free port number
    port = probe.local_address[1]
    probe.close()
    with pytest.raises(TransportError, match="Zenoh"):
        open_transport(f"zenoh://127.0.0.1:{port}/nobody", role="client", connect_timeout_s=0.3)


def test_zenoh_port_zero_only_for_peer_server():
    with pytest.raises(ValueError, match="port 0"):
        open_transport("zenoh://127.0.0.1:0/x", role="client")


# ------------------------------------------------------------------ Zenoh runtime defaults
_RUNTIME_PROBE = """
import json, os, sys
from hapticproxy.protocol.transport import open_transport
from hapticproxy.protocol.transport.zenoh_backend import zenoh_thread_ids
with open_transport("zenoh://127.0.0.1:0/runtime-probe", role="server") as server, \
        open_transport(server.url, role="client"):  # a link: Zenoh starts its RX pool lazily
    names = []
    for tid in zenoh_thread_ids():
        with open(f"/proc/self/task/{tid}/comm") as f:
            names.append(f.read().strip())
    print(json.dumps({"runtime": os.environ.get("ZENOH_RUNTIME"), "names": names}))
"""


def _probe_runtime(env_runtime):
    import json
    import subprocess

    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if env_runtime is not None:
        env["ZENOH_RUNTIME"] = env_runtime
    out = subprocess.run([sys.executable, "-c", _RUNTIME_PROBE], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="thread names from /proc")
def test_zenoh_runtime_defaults_to_one_rx_worker_unless_the_deployment_sets_one():
    from hapticproxy.protocol.transport.zenoh_backend import DEFAULT_ZENOH_RUNTIME

    ours = _probe_runtime(None)
    assert ours["runtime"] == DEFAULT_ZENOH_RUNTIME
    assert sum(n.startswith("rx-") for n in ours["names"]) == 1
    assert all(n.split("-")[0] in ("rx", "tx", "app", "acc", "net") for n in ours["names"])
    theirs = _probe_runtime("(rx: (worker_threads: 3))")  # a deployment's own setting wins
    assert theirs["runtime"] == "(rx: (worker_threads: 3))"
    assert sum(n.startswith("rx-") for n in theirs["names"]) == 3
