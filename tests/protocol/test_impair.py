"""The impairing UDP relay does exactly what its seeded plan says (counts, never timings).

Most tests drive the relay by hand (``relay.step()``): on Linux loopback a ``sendto`` has queued
the datagram at the receiving socket by the time it returns, so after a step every datagram the
relay forwarded is already waiting at its destination. Delay and jitter are checked against an
injected fake clock.
"""
from __future__ import annotations

import time

import pytest

from hapticproxy.protocol.transport import open_transport
from hapticproxy.testing.impair import GilbertElliott, Impairment, ImpairingRelay

N = 2000
SIZE = 64
CHUNK = 100  # datagrams sent between relay steps (well inside every socket buffer)


def _payload(i: int) -> bytes:
    return i.to_bytes(4, "big") + bytes((i + k) % 251 for k in range(SIZE - 4))


def _seq(data: bytes) -> int:
    return int.from_bytes(data[:4], "big")


@pytest.fixture
def rig():
    opened = []

    def make(c2s=None, s2c=None, clock=time.monotonic):
        server = open_transport("udp://127.0.0.1:0", role="server", rcvbuf_bytes=4 << 20)
        relay = ImpairingRelay(server.local_address, c2s=c2s, s2c=s2c, clock=clock)
        client = open_transport(relay.url, role="client", rcvbuf_bytes=4 << 20)
        opened.extend([client, relay, server])
        return server, relay, client

    yield make
    for thing in opened:
        thing.close()


def _push_c2s(relay, client, n=N):
    for start in range(0, n, CHUNK):
        for i in range(start, min(n, start + CHUNK)):
            assert client.send(_payload(i))
        relay.step()
    relay.step()


def _drain(t):
    out = []
    while (item := t.recv()) is not None:
        out.append(item)
    return out


def _relayed(rig, imp):
    """N datagrams pushed client -> server through a relay impairing them with ``imp``: the relay
    and the (datagram, peer) pairs the server received, in order."""
    server, relay, client = rig(c2s=imp)
    _push_c2s(relay, client)
    return relay, _drain(server)


def test_uniform_loss_drops_exactly_the_planned_datagrams(rig):
    imp = Impairment(loss=0.3, seed=7)
    relay, arrived = _relayed(rig, imp)
    got = [_seq(d) for d, _ in arrived]
    plan = imp.plan([SIZE] * N)
    expected = [i for i, d in enumerate(plan) if not d.lost]
    assert got == expected
    c = relay.c2s.counters
    assert c.received == N and c.lost == N - len(expected) and c.forwarded == len(expected)
    assert 0.25 < c.lost / N < 0.35  # the seeded stream really is ~30 % loss


def _mean_run_length(lost_flags):
    runs, run = [], 0
    for lost in lost_flags:
        if lost:
            run += 1
        elif run:
            runs.append(run)
            run = 0
    if run:
        runs.append(run)
    return sum(runs) / len(runs)


def test_gilbert_elliott_loss_comes_in_bursts(rig):
    burst = GilbertElliott(p_good_to_bad=0.05, p_bad_to_good=0.25)
    imp = Impairment(burst=burst, seed=11)
    relay, arrived = _relayed(rig, imp)
    received = {_seq(d) for d, _ in arrived}
    lost_flags = [i not in received for i in range(N)]
    assert lost_flags == [d.lost for d in imp.plan([SIZE] * N)]
    assert relay.c2s.counters.lost == sum(lost_flags)
    # Same mean loss, uniform: bursts of the Gilbert chain are far longer than chance runs.
    uniform = Impairment(loss=burst.mean_loss, seed=11).plan([SIZE] * N)
    assert abs(sum(lost_flags) / N - burst.mean_loss) < 0.05
    assert _mean_run_length(lost_flags) > 2 * _mean_run_length([d.lost for d in uniform])
    assert _mean_run_length(lost_flags) > 3.0  # 1 / p_bad_to_good = 4 expected


def test_duplication_adds_exactly_the_planned_copies(rig):
    imp = Impairment(duplicate=0.25, seed=3)
    relay, arrived = _relayed(rig, imp)
    got = [_seq(d) for d, _ in arrived]
    plan = imp.plan([SIZE] * N)
    doubled = {i for i, d in enumerate(plan) if d.copies == 2}
    assert 0 < len(doubled) == relay.c2s.counters.duplicated
    assert len(got) == N + len(doubled)
    counts = {}
    for s in got:
        counts[s] = counts.get(s, 0) + 1
    assert {s for s, k in counts.items() if k == 2} == doubled
    assert set(counts) == set(range(N)) and max(counts.values()) == 2


def test_corruption_flips_exactly_one_planned_bit(rig):
    imp = Impairment(corrupt=0.2, seed=5)
    relay, arrived = _relayed(rig, imp)
    got = [d for d, _ in arrived]
    assert len(got) == N  # corruption never drops
    plan = imp.plan([SIZE] * N)
    changed = 0
    for i, (data, d) in enumerate(zip(got, plan)):
        original = bytearray(_payload(i))
        if d.corrupt_at is None:
            assert data == bytes(original)
        else:
            byte, bit = d.corrupt_at
            original[byte] ^= 1 << bit
            assert data == bytes(original)
            changed += 1
    assert changed == relay.c2s.counters.corrupted
    assert 0.15 < changed / N < 0.25


def test_reordering_swaps_exactly_the_planned_neighbours(rig):
    imp = Impairment(reorder=0.2, seed=9)
    server, relay, client = rig(c2s=imp)
    _push_c2s(relay, client)
    # The last datagram may be held waiting for a successor: a clock far in the future frees it.
    relay.clock = lambda: time.monotonic() + 3600
    relay.step()
    got = [_seq(d) for d, _ in _drain(server)]
    expected, held = [], None
    for i, d in enumerate(imp.plan([SIZE] * N)):
        if held is None and d.hold:
            held = i
            continue
        expected.append(i)
        if held is not None:
            expected.append(held)
            held = None
    if held is not None:
        expected.append(held)
    assert got == expected
    swaps = sum(1 for a, b in zip(got, got[1:]) if a > b)
    assert swaps == relay.c2s.counters.reordered > 0


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def test_delay_and_jitter_release_datagrams_when_due(rig):
    clock = FakeClock()
    imp = Impairment(delay_s=0.010, jitter_s=0.004, seed=4)
    server, relay, client = rig(s2c=imp, clock=clock)
    assert client.send(b"hello")
    relay.step()  # c2s is unimpaired: forwarded at once
    data, peer = server.recv()
    assert data == b"hello"
    n = 50
    for i in range(n):
        assert server.send(_payload(i), peer)
    relay.step()
    delays = [d.delays_s[0] for d in imp.plan([SIZE] * n)]
    assert min(delays) >= 0.006 and max(delays) <= 0.014
    assert _drain(client) == []  # nothing is due at t = 0
    delivered = []
    for t in (0.0059, 0.008, 0.010, 0.012, 0.0141):
        clock.now_s = t
        relay.step()
        delivered.extend(_seq(d) for d, _ in _drain(client))
        assert sorted(delivered) == sorted(i for i, dl in enumerate(delays) if dl <= t)
    assert len(delivered) == n
    # Jitter of +-4 ms on datagrams sent together reorders them, as netem does.
    assert delivered != sorted(delivered)
    assert delivered == sorted(range(n), key=lambda i: (delays[i], i))


def test_threaded_relay_keeps_clients_apart_and_counts_both_directions(rig):
    server, relay, client_a = rig(c2s=Impairment(loss=0.2, seed=1), s2c=Impairment(loss=0.2, seed=2))
    client_b = open_transport(relay.url, role="client")
    try:
        relay.start()
        peers = {}
        for i in range(200):
            client_a.send(b"a%03d" % i)
            client_b.send(b"b%03d" % i)
        # Wait (hang guard only) until the relay has dealt with every datagram: forwarded ones
        # are then already queued at their destination socket.
        c2s, s2c = relay.c2s.counters, relay.s2c.counters
        deadline = time.monotonic() + 10
        while c2s.forwarded + c2s.lost < 400 and time.monotonic() < deadline:
            time.sleep(0.001)
        echoed = 0
        for data, peer in _drain(server):
            peers.setdefault(data[:1], set()).add(peer)
            assert server.send(b"ack-" + data, peer)
            echoed += 1
        while s2c.forwarded + s2c.lost < echoed and time.monotonic() < deadline:
            time.sleep(0.001)
        acks_a, acks_b = _drain(client_a), _drain(client_b)
    finally:
        client_b.close()
    assert len(peers[b"a"]) == 1 and len(peers[b"b"]) == 1 and peers[b"a"] != peers[b"b"]
    assert all(d.startswith(b"ack-a") for d, _ in acks_a)
    assert all(d.startswith(b"ack-b") for d, _ in acks_b)
    assert echoed == c2s.forwarded
    assert c2s.received == 400 and c2s.forwarded == 400 - c2s.lost
    assert s2c.received == c2s.forwarded
    assert len(acks_a) + len(acks_b) == s2c.forwarded == s2c.received - s2c.lost
    assert c2s.lost > 0 and s2c.lost > 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"loss": 1.5}, "loss"),
        ({"duplicate": -0.1}, "duplicate"),
        ({"delay_s": -1}, "delay_s"),
        ({"loss": 0.1, "burst": GilbertElliott(0.1, 0.5)}, "not both"),
    ],
)
def test_bad_impairments_are_value_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Impairment(**kwargs)
    with pytest.raises(ValueError, match="p_bad_to_good"):
        GilbertElliott(0.1, 2.0)
