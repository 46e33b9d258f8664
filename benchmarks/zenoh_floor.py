"""Floor of a Zenoh round trip on this machine, with no hapticproxy code in the path.

``python -m hapticproxy.benchmarks.zenoh_floor [--json] [--variants ...] [--zenoh-runtime RON]``

A minimal ping/pong between two processes (the pong in a spawned child), measured the way
``hapticproxy bench transport`` measures the protocol's transports: a 1300-byte ping (a
32-contact ContactUpdate), a 200-byte pong (a ProxyState), back to back, the time from just
before the ping's send until the ping's poll loop holds the pong; warm-up excluded; the two
poll threads pinned to different CPUs. It separates what a Zenoh round trip costs because of
Zenoh and its Python binding from what this project's transport adds: the ``zenoh-*`` variants
call the ``zenoh`` package directly, the ``raw-*`` variants are plain non-blocking loopback
sockets (the kernel's own floor).

Variants (``--variants`` takes a comma-separated subset):

- ``raw-udp``, ``raw-tcp``: non-blocking sockets, both sides busy polling (TCP_NODELAY).
- ``zenoh-poll``: peer mode on ``tcp/127.0.0.1``, express REAL_TIME publishers with DROP
  congestion control, RingChannel subscribers polled with ``try_recv`` (what the backend does).
- ``zenoh-poll-lowlatency``: the same in Zenoh's unicast low-latency mode (QoS off).
- ``zenoh-poll-udp``, ``zenoh-poll-lowlatency-udp``: the same over a Zenoh ``udp/`` link.
- ``zenoh-block``: ``zenoh-poll`` receiving with the blocking ``recv()`` instead.
- ``zenoh-callback``, ``zenoh-callback-lowlatency``: the pong answers from a subscriber callback
  (on Zenoh's RX thread, holding the GIL), the ping still polls.

Poll loops yield (``sched_yield``) after ``--idle-every`` empty polls (0: pure busy poll).
``--io-threads other`` pins each process's Zenoh runtime threads to the CPUs its poller does
not use (``same``: to the poller's CPU; ``float``: left alone). ``--zenoh-runtime`` sets
``ZENOH_RUNTIME`` for both processes (default: the backend's ``DEFAULT_ZENOH_RUNTIME``).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import socket
import statistics
import sys
import time

from .bench_transport import pin_this_thread, place_io_threads, selected, set_io_thread_affinity
from ..protocol.transport.zenoh_backend import DEFAULT_ZENOH_RUNTIME

PAYLOAD = 1300
REPLY = 200
SEQ = 8
VARIANTS = ("raw-udp", "raw-tcp", "zenoh-poll", "zenoh-poll-lowlatency", "zenoh-poll-udp",
            "zenoh-poll-lowlatency-udp", "zenoh-block", "zenoh-callback", "zenoh-callback-lowlatency")


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------ raw sockets
def _raw_pong(variant: str, port: int, conn, cpu) -> None:
    reply = bytearray(REPLY)
    if variant == "raw-udp":
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", port))
        s.setblocking(False)
        conn.send("ready")
        pin_this_thread(cpu)
        while True:
            try:
                data, addr = s.recvfrom(65536)
            except BlockingIOError:
                continue
            if data == b"stop":
                break
            reply[:SEQ] = data[:SEQ]
            s.sendto(reply, addr)
        s.close()
        return
    ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    ls.bind(("127.0.0.1", port))
    ls.listen(1)
    conn.send("ready")
    s, _ = ls.accept()
    ls.close()
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    s.setblocking(False)
    pin_this_thread(cpu)
    buf = bytearray()
    while True:
        try:
            chunk = s.recv(65536)
        except BlockingIOError:
            continue
        if not chunk:
            break
        buf += chunk
        while len(buf) >= PAYLOAD:
            reply[:SEQ] = buf[:SEQ]
            del buf[:PAYLOAD]
            s.sendall(reply)
    s.close()


def _raw_ping(variant: str, port: int, n: int, warmup: int, cpu) -> list[int]:
    clock = time.perf_counter_ns
    out = []
    msg = bytearray(PAYLOAD)
    if variant == "raw-udp":
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.connect(("127.0.0.1", port))
    else:
        s = socket.create_connection(("127.0.0.1", port))
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    s.setblocking(False)
    pin_this_thread(cpu)
    buf = bytearray()
    for i in range(warmup + n):
        msg[:SEQ] = i.to_bytes(SEQ, "little")
        t0 = clock()
        s.sendall(msg)
        if variant == "raw-udp":
            while True:
                try:
                    data = s.recv(65536)
                except BlockingIOError:
                    continue
                if data[:SEQ] == msg[:SEQ]:
                    break
        else:
            while len(buf) < REPLY:
                try:
                    buf += s.recv(65536)
                except BlockingIOError:
                    continue
            del buf[:REPLY]
        if i >= warmup:
            out.append(clock() - t0)
    if variant == "raw-udp":
        s.send(b"stop")
    s.close()
    return out


# ------------------------------------------------------------------------------ zenoh
def _zenoh_config(variant: str, port: int, listen: bool):
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    endpoint = json.dumps([f"{'udp' if variant.endswith('-udp') else 'tcp'}/127.0.0.1:{port}"])
    cfg.insert_json5("listen/endpoints" if listen else "connect/endpoints", endpoint)
    cfg.insert_json5("connect/endpoints" if listen else "listen/endpoints", "[]")
    cfg.insert_json5("transport/shared_memory/enabled", "false")
    if "lowlatency" in variant:
        cfg.insert_json5("transport/unicast/lowlatency", "true")
        cfg.insert_json5("transport/unicast/qos/enabled", "false")
    return cfg


def _publisher(session, key: str):
    import zenoh

    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP,
                                     priority=zenoh.Priority.REAL_TIME, express=True)


def _receiver(variant: str, handler, idle_every: int):
    if variant == "zenoh-block":
        return handler.recv
    try_recv, yield_ = handler.try_recv, os.sched_yield

    def poll():
        empty = 0
        while True:
            sample = try_recv()
            if sample is not None:
                return sample
            empty += 1
            if idle_every and empty >= idle_every:
                yield_()
                empty = 0

    return poll


def _zenoh_pong(variant: str, port: int, conn, cpu, idle_every: int, io_threads: str) -> None:
    import zenoh

    session = zenoh.open(_zenoh_config(variant, port, listen=True))
    pub = _publisher(session, "floor/pong")
    reply = bytearray(REPLY)
    if variant.startswith("zenoh-callback"):
        stop = []

        def on_ping(sample):
            data = sample.payload.to_bytes()
            if data == b"stop":
                stop.append(True)
                return
            reply[:SEQ] = data[:SEQ]
            pub.put(bytes(reply))

        sub = session.declare_subscriber("floor/ping", on_ping)
        conn.send("ready")
        while not stop:
            time.sleep(0.01)
    else:
        sub = session.declare_subscriber("floor/ping", zenoh.handlers.RingChannel(64))
        conn.send("ready")
        pin_this_thread(cpu)
        place_io_threads(io_threads, cpu)
        recv = _receiver(variant, sub.handler, idle_every)
        while True:
            data = recv().payload.to_bytes()
            if data == b"stop":
                break
            reply[:SEQ] = data[:SEQ]
            pub.put(bytes(reply))
    sub.undeclare()
    session.close()


def _zenoh_ping(variant: str, port: int, n: int, warmup: int, cpu, idle_every: int, io_threads: str) -> list[int]:
    import zenoh

    session = zenoh.open(_zenoh_config(variant, port, listen=False))
    sub = session.declare_subscriber("floor/pong", zenoh.handlers.RingChannel(64))
    pub = _publisher(session, "floor/ping")
    deadline = time.monotonic() + 10
    while not pub.matching_status.matching:
        if time.monotonic() > deadline:
            raise RuntimeError("the pong's subscriber never matched")
        time.sleep(0.001)
    time.sleep(0.2)  # the pong's publisher must also have seen our subscriber
    pin_this_thread(cpu)
    place_io_threads(io_threads, cpu)
    recv = _receiver(variant, sub.handler, idle_every)
    msg = bytearray(PAYLOAD)
    clock = time.perf_counter_ns
    out = []
    for i in range(warmup + n):
        msg[:SEQ] = i.to_bytes(SEQ, "little")
        t0 = clock()
        pub.put(bytes(msg))
        while recv().payload.to_bytes()[:SEQ] != msg[:SEQ]:
            pass
        if i >= warmup:
            out.append(clock() - t0)
    pub.put(b"stop")
    time.sleep(0.1)
    session.close()
    return out


def _pong(variant, port, conn, cpu, idle_every, io_threads, runtime):
    if runtime is not None:
        os.environ["ZENOH_RUNTIME"] = runtime
    if variant.startswith("raw"):
        _raw_pong(variant, port, conn, cpu)
    else:
        _zenoh_pong(variant, port, conn, cpu, idle_every, io_threads)


def run(variant: str, n: int, warmup: int, idle_every: int = 10, pin: bool = True, io_threads: str = "float") -> dict:
    """One variant, in a fresh child for the pong; returns a row like ``bench transport``'s."""
    ctx = mp.get_context("spawn")
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    pin = pin and len(cpus) >= 2
    pong_cpu, ping_cpu = (cpus[-1], cpus[0]) if pin else (None, None)
    port = _free_port(socket.SOCK_DGRAM if variant.endswith("-udp") else socket.SOCK_STREAM)
    runtime = os.environ.get("ZENOH_RUNTIME")
    parent_conn, child_conn = ctx.Pipe()
    child = ctx.Process(target=_pong, args=(variant, port, child_conn, pong_cpu, idle_every, io_threads, runtime),
                        daemon=True)
    child.start()
    saved = os.sched_getaffinity(0) if pin else None
    try:
        if not parent_conn.poll(30):
            raise RuntimeError(f"{variant}: the pong did not start")
        parent_conn.recv()
        if variant.startswith("raw"):
            rtts = _raw_ping(variant, port, n, warmup, ping_cpu)
        else:
            rtts = _zenoh_ping(variant, port, n, warmup, ping_cpu, idle_every, io_threads)
    finally:
        if saved is not None:
            os.sched_setaffinity(0, saved)
            set_io_thread_affinity(saved)
        child.join(10)
        if child.is_alive():
            child.terminate()
            child.join(5)
    rtts.sort()
    k = len(rtts)
    return {"variant": variant, "exchanges": k, "warmup": warmup,
            "rtt_us": {"p50": round(rtts[k // 2] / 1e3, 1), "p99": round(rtts[min(k - 1, int(0.99 * k))] / 1e3, 1),
                       "max": round(rtts[-1] / 1e3, 1), "mean": round(statistics.fmean(rtts) / 1e3, 1)},
            "idle_every": idle_every, "pinned": pin, "io_threads": io_threads if pin else "float",
            "zenoh_runtime": None if variant.startswith("raw") else runtime}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hapticproxy.benchmarks.zenoh_floor", description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print a JSON list of rows")
    p.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated, from: " + ", ".join(VARIANTS))
    p.add_argument("--exchanges", type=int, default=5000)
    p.add_argument("--warmup", type=int, default=500)
    p.add_argument("--idle-every", type=int, default=10, help="empty polls before a sched_yield (0: never)")
    p.add_argument("--io-threads", choices=("other", "same", "float"), default="float")
    p.add_argument("--no-pin", action="store_true", help="do not pin the two poll threads")
    p.add_argument("--zenoh-runtime", default=None, metavar="RON",
                   help=f"ZENOH_RUNTIME for both processes (default {DEFAULT_ZENOH_RUNTIME!r})")
    args = p.parse_args(argv)
    variants = selected(p, args.variants, VARIANTS, "variant")
    if args.exchanges < 1 or args.warmup < 0:
        p.error("--exchanges must be >= 1 and --warmup >= 0")
    # Before any Zenoh use in this process: Zenoh reads it when its runtime starts.
    os.environ["ZENOH_RUNTIME"] = args.zenoh_runtime if args.zenoh_runtime is not None else DEFAULT_ZENOH_RUNTIME
    rows = []
    for v in variants:
        row = run(v, args.exchanges, args.warmup, args.idle_every, not args.no_pin, args.io_threads)
        rows.append(row)
        if not args.json:
            r = row["rtt_us"]
            print(f"{v:26s} p50 {r['p50']:7.1f} us  p99 {r['p99']:7.1f} us  max {r['max']:8.1f} us", flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
