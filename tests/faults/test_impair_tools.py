"""The fault-injection tools do what they say (counts and byte contents, a fake clock for time):
the impairing TCP proxy (delay without reordering, stall, reset) and the message-impairing
transport wrapper (the relay's seeded decisions, applied to any transport)."""
from __future__ import annotations

import socket

import pytest

from hapticproxy.protocol.transport import open_transport
from hapticproxy.testing.impair import GilbertElliott, ImpairedTransport, Impairment
from hapticproxy.testing.impair_tcp import ImpairingTcpProxy


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def tcp_rig():
    made = []

    def make(**kw):
        upstream = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        upstream.bind(("127.0.0.1", 0))
        upstream.listen(4)
        clock = FakeClock()
        proxy = ImpairingTcpProxy(upstream.getsockname(), clock=clock, **kw)
        client = socket.create_connection(proxy.address, timeout=5)
        proxy.step()  # accept, connect upstream
        server, _ = upstream.accept()
        server.settimeout(5)
        client.settimeout(5)
        made.extend([client, server, upstream, proxy])
        return proxy, clock, client, server

    yield make
    for thing in made:
        thing.close()


def _recv_exactly(sock: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            break
        out += chunk
    return out


def _nothing_waiting(sock: socket.socket) -> bool:
    sock.setblocking(False)
    try:
        sock.recv(1, socket.MSG_PEEK)
        return False
    except BlockingIOError:
        return True
    finally:
        sock.setblocking(True)
        sock.settimeout(5)


def test_tcp_delay_and_jitter_never_reorder_bytes(tcp_rig):
    proxy, clock, client, server = tcp_rig(delay_s=0.02, jitter_s=0.015, seed=3)
    sent = b""
    for i in range(50):
        data = bytes([i]) * (10 + i)
        client.sendall(data)
        sent += data
        proxy.step()  # read at clock t: released at t + 20 ms +- 15 ms, but never before earlier bytes
        if i == 0:
            assert _nothing_waiting(server)  # the delay is at least 5 ms
        clock.t += 0.001
    clock.t += 1.0
    proxy.step()
    assert _recv_exactly(server, len(sent)) == sent
    assert proxy.counters.bytes_c2s == len(sent)
    server.sendall(b"reply")
    proxy.step()
    clock.t += 0.036
    proxy.step()
    assert _recv_exactly(client, 5) == b"reply"


def test_tcp_stall_holds_everything_then_releases_it_in_order(tcp_rig):
    proxy, clock, client, server = tcp_rig()
    proxy.stall(0.3)
    client.sendall(b"during the stall")
    server.sendall(b"both ways")
    proxy.step()
    clock.t += 0.29
    proxy.step()
    assert _nothing_waiting(server) and _nothing_waiting(client)
    clock.t += 0.02
    proxy.step()
    assert _recv_exactly(server, 16) == b"during the stall"
    assert _recv_exactly(client, 9) == b"both ways"
    assert proxy.counters.stalls == 1


def test_tcp_reset_tears_the_link_down_and_new_links_are_accepted(tcp_rig):
    proxy, clock, client, server = tcp_rig()
    client.sendall(b"x")
    proxy.step()
    assert _recv_exactly(server, 1) == b"x"
    assert proxy.reset_links() == 1
    with pytest.raises((ConnectionResetError, ConnectionAbortedError)):
        client.sendall(b"y" * 100000)
        client.recv(1)
    assert proxy.counters.reset == 1 and proxy.connections == 0
    again = socket.create_connection(proxy.address, timeout=5)
    try:
        proxy.step()
        assert proxy.counters.accepted == 2 and proxy.connections == 1
    finally:
        again.close()


def test_tcp_proxy_carries_zenoh_end_to_end():
    server = open_transport("zenoh://127.0.0.1:0/imp", role="server")
    try:
        with ImpairingTcpProxy(("127.0.0.1", server.port), delay_s=0.005) as proxy:
            proxy.start()
            client = open_transport(f"zenoh://127.0.0.1:{proxy.address[1]}/imp", role="client")
            try:
                client.send(b"through the proxy")
                import time

                t_end = time.monotonic() + 10
                got = None
                while got is None and time.monotonic() < t_end:
                    got = server.recv()
                    time.sleep(0.001)
                assert got is not None and got[0] == b"through the proxy"
                assert proxy.counters.accepted >= 1 and proxy.counters.bytes_c2s > 0
            finally:
                client.close()
    finally:
        server.close()


_names = iter(range(10**6))


@pytest.fixture
def mem_pair():
    name = f"mem://impair-wrap-{next(_names)}"
    server = open_transport(name, role="server")
    client = open_transport(name, role="client")
    yield server, client
    client.close()
    server.close()


def _drain(t):
    out = []
    while (item := t.recv()) is not None:
        out.append(item[0])
    return out


@pytest.mark.parametrize("imp", [
    Impairment(loss=0.3, seed=7),
    Impairment(burst=GilbertElliott(0.1, 0.3), seed=8),
    Impairment(duplicate=0.2, seed=9),
    Impairment(corrupt=0.2, seed=10),
])
def test_wrapped_send_does_what_the_seeded_plan_says(mem_pair, imp):
    server, inner = mem_pair
    clock = FakeClock()
    client = ImpairedTransport(inner, send=imp, clock=clock)
    payloads = [i.to_bytes(4, "big") * 8 for i in range(400)]
    for p in payloads:
        assert client.send(p)
    plan = imp.plan([len(p) for p in payloads])
    got = _drain(server)
    expected = []
    for p, d in zip(payloads, plan):
        if d.lost:
            continue
        if d.corrupt_at is not None:
            b = bytearray(p)
            b[d.corrupt_at[0]] ^= 1 << d.corrupt_at[1]
            p = bytes(b)
        expected.extend([p] * d.copies)
    assert got == expected
    c = client.counters_send
    assert c.received == 400 and c.lost == sum(d.lost for d in plan)
    assert c.forwarded == len(expected)


def test_wrapped_delay_reorder_and_receive_side(mem_pair):
    server, inner = mem_pair
    clock = FakeClock()
    client = ImpairedTransport(inner, send=Impairment(delay_s=0.05, seed=1), recv=Impairment(reorder=1.0, seed=2),
                               clock=clock)
    client.send(b"late")
    assert server.recv() is None  # held for 50 ms
    clock.t += 0.06
    assert client.recv() is None  # any call releases what is due
    data, peer = server.recv()
    assert data == b"late"
    # receive side: every datagram is held and released after the next one (adjacent swaps)
    for p in (b"a", b"b", b"c", b"d"):
        server.send(p, peer)
    got = _drain(client)
    assert got == [b"b", b"a", b"d", b"c"]
    assert client.counters_recv.reordered == 2
    assert client.url == inner.url and client.default_peer == inner.default_peer
