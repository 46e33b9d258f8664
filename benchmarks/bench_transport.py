"""``hapticproxy bench transport``: update -> acknowledgement round trip between two processes.

The environment side (this process) sends a ContactUpdate-sized datagram and waits for the
ProxyState-sized acknowledgement from an echo server running in a child process; the time from
just before ``send`` to the ``recv_into`` that returns the acknowledgement is one round trip.
Both sides poll their transport without blocking (what the haptic loop does at the start of a
step) and the echo side answers each update at once. By default the two polling threads are
pinned to different CPUs (an unpinned busy poller that shares a core with the other side's
sleeping thread delayed its wake-up by a whole scheduler slice, ~12 ms, in 1% of paced UDP
exchanges); UDP pollers spin, Zenoh pollers ``sched_yield`` every 10 empty polls so Zenoh's
own I/O threads get the core (``--idle-every``). In the ``zenoh-lowlatency`` rows each
process's Zenoh runtime threads are also pinned, to the CPU its own poller does not use
(``--io-threads``, see :data:`DEFAULT_IO_THREADS`). Zenoh's thread pools are those the backend
asks for (``zenoh_backend.DEFAULT_ZENOH_RUNTIME``) unless ``--zenoh-runtime`` sets others.

How much of a Zenoh round trip is Zenoh itself (and its Python binding) rather than this
project's transport: ``python -m hapticproxy.benchmarks.zenoh_floor`` measures a bare Zenoh
ping/pong and raw loopback sockets the same way.

Two schedules per transport:

- ``paced``: one exchange per period (1 kHz by default), the haptic rate: sleep most of the
  gap, spin the last ``SPIN_BEFORE_NS`` so the send leaves on time;
- back-to-back (``paced: false``): the next update leaves as soon as the acknowledgement is in.

Rows (``--json`` prints a JSON list): ``transport``, ``paced``, ``rate_hz`` (null when
back-to-back), ``exchanges``, ``warmup``, ``update_bytes``, ``ack_bytes``, ``lost`` (updates
whose acknowledgement did not come within ``--timeout-ms``; they are excluded from the
statistics), ``rtt_us`` with ``p50``, ``p99``, ``max`` and ``mean``, ``options`` (the
transport options used), ``poll`` (the idle policy, the pinning and where Zenoh's threads
went) and, for Zenoh rows, ``zenoh_runtime`` (the ``ZENOH_RUNTIME`` in force). ``transport`` is ``udp``,
``zenoh`` (default options) or ``zenoh-lowlatency`` (Zenoh's unicast low-latency mode).
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import random
import statistics
import sys
import time

from ..protocol.logs import doc_summary
from ..protocol.transport import open_transport
from ..protocol.jsonout import print_json

UPDATE_BYTES = 1300  # a 32-contact ContactUpdate
ACK_BYTES = 200  # a ProxyState acknowledgement
STOP = b"\xffbench-stop"
SPIN_BEFORE_NS = 200_000  # paced mode: busy-wait the last 0.2 ms before each send
SEQ_BYTES = 8


def pin_this_thread(cpu: int | None) -> None:
    # Pin only the calling (polling) thread: on Linux sched_setaffinity(0) applies to the
    # calling thread, so backend I/O threads started earlier (Zenoh's) still float.
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpu})


def set_io_thread_affinity(cpus) -> None:
    """Pin this process's Zenoh runtime threads to ``cpus`` (also to unpin them again: Zenoh's
    threads outlive a session)."""
    from ..protocol.transport.zenoh_backend import zenoh_thread_ids

    for tid in zenoh_thread_ids():
        try:
            os.sched_setaffinity(tid, cpus)
        except OSError:  # ended meanwhile, or a CPU outside our cgroup
            pass


def place_io_threads(policy: str, poll_cpu: int | None) -> None:
    """Pin this process's Zenoh runtime threads: ``other`` = every CPU but the poller's,
    ``same`` = the poller's CPU, ``float`` = leave them to the scheduler."""
    if policy == "float" or poll_cpu is None or not hasattr(os, "sched_setaffinity"):
        return
    set_io_thread_affinity({poll_cpu} if policy == "same" else set(range(os.cpu_count() or 1)) - {poll_cpu})


def selected(parser: argparse.ArgumentParser, text: str, known, what: str) -> list[str]:
    """The comma-separated names of ``text``; one not in ``known`` is a usage error."""
    names = [t.strip() for t in text.split(",") if t.strip()]
    for t in names:
        if t not in known:
            parser.error(f"unknown {what} {t!r} (choose from {', '.join(known)})")
    return names


def _make_idle(idle_every: int, idle_sleep_us: float):
    """What a poll loop does after ``idle_every`` empty polls in a row (None: pure busy poll).

    On a machine with few cores a pure busy poll on both sides starves the backend's own I/O
    threads (Zenoh's); yielding (``idle_sleep_us`` 0) or a short sleep gives them the core.
    """
    if idle_every <= 0:
        return None
    if idle_sleep_us <= 0:
        return os.sched_yield
    sleep_s = idle_sleep_us / 1e6
    return lambda: time.sleep(sleep_s)


def _poll(transport, buf: bytearray, idle, idle_every: int, deadline_ns: int | None = None,
          clock=time.perf_counter_ns) -> tuple[int, object]:
    """Poll ``transport`` until a datagram is in ``buf``: its length and sender; ``(0, None)`` once
    ``clock()`` passes ``deadline_ns``. ``idle`` (see :func:`_make_idle`) runs after every
    ``idle_every`` empty polls in a row."""
    empty = 0
    while True:
        n, peer = transport.recv_into(buf)
        if peer is not None:
            return n, peer
        empty += 1
        if idle is not None and empty >= idle_every:
            idle()
            empty = 0
        if deadline_ns is not None and clock() > deadline_ns:
            return 0, None


def _echo_server(url: str, options: dict, conn, idle_every: int, idle_sleep_us: float, cpu: int | None,
                 io_threads: str = "float") -> None:
    """Child process: answer every update with an ack carrying the update's sequence bytes."""
    server = open_transport(url, role="server", **options)
    pin_this_thread(cpu)
    place_io_threads(io_threads, cpu)
    try:
        conn.send(server.url)
        buf = bytearray(server.max_packet_bytes)
        ack = bytearray(random.Random(2).randbytes(ACK_BYTES))
        idle = _make_idle(idle_every, idle_sleep_us)
        while True:
            n, peer = _poll(server, buf, idle, idle_every)
            if buf[:n] == STOP:
                server.send(STOP, peer)
                break
            ack[:SEQ_BYTES] = buf[:SEQ_BYTES]
            server.send(ack, peer)
    finally:
        server.close()
        conn.close()


def _percentile(sorted_values: list[int], q: float) -> int:
    # Nearest-rank percentile: a value that was actually measured.
    k = max(0, min(len(sorted_values) - 1, int(round(q * len(sorted_values) + 0.5)) - 1))
    return sorted_values[k]


def run_one(
    transport: str,
    paced: bool,
    exchanges: int,
    warmup: int,
    rate_hz: float,
    timeout_ms: float,
    options: dict,
    idle_every: int,
    idle_sleep_us: float,
    pin: bool,
    io_threads: str = "float",
) -> dict:
    url = {"udp": "udp://127.0.0.1:0", "zenoh": "zenoh://127.0.0.1:0/bench"}[transport]
    ctx = mp.get_context("spawn")  # no fork of a process that may host Zenoh threads
    parent_conn, child_conn = ctx.Pipe()
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    pin = pin and len(cpus) >= 2
    child_cpu, parent_cpu = (cpus[-1], cpus[0]) if pin else (None, None)
    child = ctx.Process(
        target=_echo_server, args=(url, options, child_conn, idle_every, idle_sleep_us, child_cpu, io_threads),
        daemon=True,
    )
    child.start()
    client = None
    saved_affinity = None
    try:
        deadline = time.monotonic() + 30
        while not parent_conn.poll(0.05):
            if not child.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"{transport} echo server did not start (exit code {child.exitcode})")
        server_url = parent_conn.recv()
        client = open_transport(server_url, role="client", **options)
        if pin:
            saved_affinity = os.sched_getaffinity(0)
            pin_this_thread(parent_cpu)
            place_io_threads(io_threads, parent_cpu)
        rng = random.Random(1)
        update = bytearray(rng.randbytes(UPDATE_BYTES))
        buf = bytearray(client.max_packet_bytes)
        period_ns = int(1e9 / rate_hz)
        timeout_ns = int(timeout_ms * 1e6)
        rtts_ns: list[int] = []
        idle = _make_idle(idle_every, idle_sleep_us)
        lost = 0
        clock = time.perf_counter_ns
        next_send_ns = clock() + period_ns
        total = warmup + exchanges
        for i in range(total):
            if paced:
                now = clock()
                gap = next_send_ns - now
                if gap > SPIN_BEFORE_NS:
                    time.sleep((gap - SPIN_BEFORE_NS) / 1e9)
                while clock() < next_send_ns:
                    pass
                next_send_ns += period_ns
            seq = i.to_bytes(SEQ_BYTES, "little")
            update[:SEQ_BYTES] = seq
            t0 = clock()
            client.send(update)
            while True:
                n, peer = _poll(client, buf, idle, idle_every, t0 + timeout_ns, clock)
                t1 = clock()
                if peer is None:
                    if i >= warmup:
                        lost += 1
                    break
                if buf[:SEQ_BYTES] == seq:
                    if i >= warmup:
                        rtts_ns.append(t1 - t0)
                    break
                # else a late ack of an earlier, already-counted-lost update
            if paced and clock() > next_send_ns + 10 * period_ns:
                next_send_ns = clock() + period_ns  # do not burst to catch up after a stall
        client.send(STOP)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            item = client.recv()
            if item is not None and item[0] == STOP:
                break
    finally:
        if saved_affinity is not None:
            os.sched_setaffinity(0, saved_affinity)
            if io_threads != "float":  # Zenoh's threads outlive the client: unpin them again
                set_io_thread_affinity(saved_affinity)
        if client is not None:
            client.close()
        child.join(10)
        if child.is_alive():
            child.terminate()
            child.join(5)
    if not rtts_ns:
        raise RuntimeError(f"{transport}: no round trip completed")
    rtts_ns.sort()
    return {
        "transport": transport,
        "paced": paced,
        "rate_hz": rate_hz if paced else None,
        "exchanges": exchanges,
        "warmup": warmup,
        "update_bytes": UPDATE_BYTES,
        "ack_bytes": ACK_BYTES,
        "lost": lost,
        "rtt_us": {
            "p50": round(_percentile(rtts_ns, 0.50) / 1e3, 1),
            "p99": round(_percentile(rtts_ns, 0.99) / 1e3, 1),
            "max": round(rtts_ns[-1] / 1e3, 1),
            "mean": round(statistics.fmean(rtts_ns) / 1e3, 1),
        },
        "options": options,
        "pinned": pin,
        "io_threads": io_threads if pin else "float",
    }


#: Transport variants the bench knows: (backend, transport options).
VARIANTS = {
    "udp": ("udp", {}),
    "zenoh": ("zenoh", {}),
    "zenoh-lowlatency": ("zenoh", {"lowlatency": True}),
}
#: Empty polls before a poll loop yields its core (0 = pure busy poll). Measured on a 2-core
#: box: UDP is best pure busy (nothing else needs the core); Zenoh's own RX/TX threads need the
#: core the poller spins on, and yielding every 10 empty polls gave the lowest p50 and p99.
DEFAULT_IDLE_EVERY = {"udp": 0, "zenoh": 10}
#: Where each process's Zenoh runtime threads go (with pinned pollers), per variant. Measured on
#: the 2-vCPU VM, 6 runs of 2,000 exchanges each: low-latency mode, whose RX thread is the only
#: Zenoh thread on the path, did best with it on the CPU its poller does not use ("other":
#: back-to-back p50 33-43 us against 62-79 floating); default mode, which also hands every put
#: to Zenoh's TX thread, did no better pinned (76-124 us against 80-109 floating), so it floats.
DEFAULT_IO_THREADS = {"zenoh": "float", "zenoh-lowlatency": "other"}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="hapticproxy bench transport", description=doc_summary(__doc__))
    parser.add_argument("--json", action="store_true", help="print a JSON list of rows")
    parser.add_argument(
        "--transports", default=",".join(VARIANTS), help=f"comma-separated, from: {', '.join(VARIANTS)}"
    )
    parser.add_argument("--exchanges", type=int, default=5000, help="measured round trips per row")
    parser.add_argument("--warmup", type=int, default=500, help="round trips run before measuring")
    parser.add_argument("--rate-hz", type=float, default=1000.0, help="paced send rate")
    parser.add_argument("--schedule", choices=("both", "paced", "back-to-back"), default="both",
                        help="paced at the haptic rate, back-to-back, or both (default)")
    parser.add_argument("--timeout-ms", type=float, default=100.0, help="an ack later than this counts as lost")
    parser.add_argument(
        "--idle-every",
        type=int,
        default=None,
        help="poll loops yield after this many empty polls (0 = pure busy poll; default per transport)",
    )
    parser.add_argument(
        "--idle-sleep-us", type=float, default=0.0, help="when idling: sleep this long (0 = sched_yield)"
    )
    parser.add_argument(
        "--no-pin", action="store_true", help="do not pin the two polling threads to different CPUs"
    )
    parser.add_argument(
        "--io-threads",
        choices=("other", "same", "float"),
        default=None,
        help="where each process's Zenoh runtime threads go when pollers are pinned: every CPU but "
        "the poller's (other), the poller's (same) or anywhere (float); default per variant: "
        + ", ".join(f"{k} {v}" for k, v in DEFAULT_IO_THREADS.items()),
    )
    parser.add_argument(
        "--zenoh-runtime",
        default=None,
        metavar="RON",
        help="set ZENOH_RUNTIME (Zenoh's process-wide thread pools, RON syntax) for both processes, "
        "e.g. '(rx: (handover: app), acc: (handover: app))'; must precede any Zenoh use in this process",
    )
    args = parser.parse_args(argv)
    if args.zenoh_runtime is not None:
        if not args.zenoh_runtime.strip():
            parser.error("--zenoh-runtime must not be empty")
        # Inherited by the spawned echo process; read by Zenoh when its runtime first starts.
        os.environ["ZENOH_RUNTIME"] = args.zenoh_runtime
    variants = selected(parser, args.transports, VARIANTS, "transport")
    if args.exchanges < 1 or args.warmup < 0:
        parser.error("--exchanges must be >= 1 and --warmup >= 0")
    schedules = {"both": (True, False), "paced": (True,), "back-to-back": (False,)}[args.schedule]
    rows = []
    for variant in variants:
        backend, options = VARIANTS[variant]
        idle_every = DEFAULT_IDLE_EVERY[backend] if args.idle_every is None else args.idle_every
        for paced in schedules:
            row = run_one(
                backend,
                paced,
                args.exchanges,
                args.warmup,
                args.rate_hz,
                args.timeout_ms,
                dict(options),
                idle_every,
                args.idle_sleep_us,
                not args.no_pin,
                (args.io_threads or DEFAULT_IO_THREADS.get(variant, "float")) if backend == "zenoh" else "float",
            )
            row["transport"] = variant
            if backend == "zenoh":
                row["zenoh_runtime"] = os.environ.get("ZENOH_RUNTIME")
            row["poll"] = {
                "idle_every": idle_every,
                "idle": (
                    "none (busy poll)"
                    if idle_every <= 0
                    else ("sleep %g us" % args.idle_sleep_us) if args.idle_sleep_us > 0 else "sched_yield"
                ),
                "pinned": row.pop("pinned"),
                "io_threads": row.pop("io_threads"),
            }
            rows.append(row)
            if not args.json:
                r = row["rtt_us"]
                sched = f"paced {row['rate_hz']:g} Hz" if paced else "back-to-back"
                print(
                    f"{variant:17s} {sched:16s} n={row['exchanges']} lost={row['lost']}  "
                    f"rtt p50 {r['p50']:7.1f} us  p99 {r['p99']:7.1f} us  max {r['max']:8.1f} us",
                    flush=True,
                )
    if args.json:
        print_json(rows, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
