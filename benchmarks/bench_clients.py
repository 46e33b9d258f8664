"""``hapticproxy bench clients``: environment-client tick cost and sustained update rate.

For every engine and scene (default: every registered engine, built-in or installed by another
package, whose library imports; every scene):

- **tick**: one engine step + contact extraction (with clustering to the requested capacity) +
  ``ContactUpdate`` encoding, timed with ``perf_counter_ns`` over ``--ticks`` ticks after
  ``--warmup`` untimed ones, ``--repeat`` times in a row, while a scripted proxy pushes the tool from its start pose 0.15 m
  along world +y, holds it there and comes back (a trapezoid with a 4 s period of simulation
  time: 1 s out, 2 s held, 1 s back), so the tool meets the scene's walls, hole or bodies and
  contacts exist. ``tick_median_us`` (all ticks), ``tick_p99_us`` (the median of the
  blocks' 99th percentiles, so one block hit by another process's time slice does not decide the
  figure; the blocks' values are in ``tick_p99_blocks_us``), ``tick_cpu_p99_us`` (99th percentile
  of the thread's CPU time per tick: what the tick costs when nothing preempts it),
  ``contacts_mean``, ``contacts_max``.
- **sustained**: a fresh engine in the same scene run by :class:`ClientRunner` back-to-back
  (``realtime=False``) for ``--seconds`` against the protocol's reference server
  (``protocol.conformance.run_reference_server``) in a child process on UDP loopback.
  ``sustained_hz`` = ContactUpdates the server acknowledged (ProxyStates received) per second;
  ``sent_hz`` = ContactUpdates sent per second. ``--seconds 0`` skips it (null).

``--json`` prints a JSON list of rows with ``engine``, ``scene`` and the figures above.
"""
from __future__ import annotations

import argparse
import gc
import math
import multiprocessing as mp
import statistics
import sys
import time

import numpy as np

from ..protocol.logs import doc_summary
from ..protocol.jsonout import print_json

PUSH_M = 0.15
PERIOD_S = 4.0


def _available_engines() -> dict:
    """Every registered engine (``hapticproxy.engines`` entry points) whose library imports."""
    from ..clients.registry import engines, load_engine_class

    registry = engines()
    out = {}
    for name in registry:
        try:
            out[name] = load_engine_class(name, registry)
        except ValueError:
            continue
    return out


def _proxy_target(start: np.ndarray, t: float, out: np.ndarray) -> np.ndarray:
    """Ramp 0.15 m along +y in the first quarter of the period, hold for half, ramp back."""
    phase = (t % PERIOD_S) / PERIOD_S
    shape = min(1.0, 4.0 * phase, 4.0 * (1.0 - phase))
    out[:] = start
    out[1] = start[1] + PUSH_M * shape
    return out


def time_ticks(engine, scene: str, *, ticks: int, warmup: int, epsilon_m: float, max_contacts: int,
               repeat: int = 3) -> dict:
    """Time ``repeat`` blocks of ``ticks`` engine ticks (step + contacts + encode) in ``scene``."""
    from ..clients.engine import ContactBuffer
    from ..protocol.codec import Codec

    info = engine.load_scene(scene)
    engine.set_epsilon(epsilon_m)
    engine.warm_up()
    codec = Codec()
    buf = ContactBuffer(max_contacts)
    pose = np.zeros(7)
    start = engine.tool_pose(np.zeros(7)).copy()
    target = np.zeros(7)
    twist = np.zeros(6)
    wrench = np.zeros(6)
    fixed_dt = 1.0 / info.env_rate_hz
    total = warmup + ticks * repeat
    times = np.zeros(ticks * repeat, dtype=np.int64)
    cpu = np.zeros(ticks * repeat, dtype=np.int64)
    counts = np.zeros(ticks * repeat, dtype=np.int64)
    perf, thread = time.perf_counter_ns, time.thread_time_ns
    gc.collect()
    for k in range(total):
        engine.drive_tool(_proxy_target(start, engine.time_s, target), twist, wrench)
        c0 = thread()
        t0 = perf()
        engine.step(engine.next_step_s() or fixed_dt)
        n = engine.contacts(buf, max_contacts)
        engine.tool_pose(pose)
        codec.encode_contact_update(1, 1, k + 1, engine.time_s, pose, buf.keys[:n], buf.position_m[:n],
                                    buf.normal[:n], buf.separation_m[:n], buf.v_constr_m_per_s[:n])
        t1 = perf()
        c1 = thread()
        if k >= warmup:
            times[k - warmup] = t1 - t0
            cpu[k - warmup] = c1 - c0
            counts[k - warmup] = n
    block_p99 = [float(np.percentile(b, 99)) for b in times.reshape(repeat, ticks)]
    return {
        "ticks": ticks * repeat,
        "tick_median_us": round(float(np.median(times)) / 1e3, 2),
        "tick_p99_us": round(statistics.median(block_p99) / 1e3, 2),
        "tick_p99_blocks_us": [round(v / 1e3, 2) for v in block_p99],
        "tick_cpu_p99_us": round(float(np.percentile(cpu, 99)) / 1e3, 2),
        "contacts_mean": round(float(counts.mean()), 2),
        "contacts_max": int(counts.max()),
    }


def _serve(conn, stop) -> None:
    """Child process: the reference server on a free UDP loopback port until ``stop`` is set."""
    from ..protocol.conformance import run_reference_server
    from ..protocol.session import ServerConfig
    from ..protocol.transport import open_transport

    t = open_transport("udp://127.0.0.1:0", role="server")
    conn.send(t.url)
    try:
        run_reference_server(t, stop, config=ServerConfig(max_sessions=4))
    finally:
        t.close()


def sustained(cls, scene: str, url: str, *, seconds: float, epsilon_m: float, max_contacts: int) -> dict:
    """Run a fresh engine back-to-back against the server at ``url`` for ``seconds``."""
    from ..clients.runner import ClientRunner

    engine = cls()
    try:
        runner = ClientRunner(engine, url, scene=scene, epsilon_m=epsilon_m, max_contacts=max_contacts,
                              realtime=False, reconnect=False, connect_timeout_s=10.0)
        t0 = time.monotonic()
        st = runner.run(duration_s=seconds)
        elapsed = time.monotonic() - t0
    finally:
        engine.close()
    return {"sustained_hz": round(st["proxy_states"] / elapsed, 1), "sent_hz": round(st["updates_sent"] / elapsed, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="hapticproxy bench clients", description=doc_summary(__doc__))
    parser.add_argument("--json", action="store_true", help="print a JSON list of rows")
    parser.add_argument("--engines", default=None, help="comma-separated engine names (default: all that import)")
    parser.add_argument("--scenes", default=None, help="comma-separated scene names (default: each engine's all)")
    parser.add_argument("--ticks", type=int, default=2000, help="timed ticks per block")
    parser.add_argument("--warmup", type=int, default=200, help="untimed ticks before timing")
    parser.add_argument("--repeat", type=int, default=3, help="timed blocks of --ticks per row")
    parser.add_argument("--seconds", type=float, default=2.0, help="sustained-rate run per row (0: skip)")
    parser.add_argument("--epsilon", type=float, default=0.005, help="epsilon [m]")
    parser.add_argument("--max-contacts", type=int, default=16, help="contact capacity")
    args = parser.parse_args(argv)
    if args.ticks < 1 or args.warmup < 0 or args.repeat < 1 or not (args.seconds >= 0) or not (1 <= args.max_contacts <= 64):
        parser.error("--ticks >= 1, --warmup >= 0, --repeat >= 1, --seconds >= 0, --max-contacts in 1..64")
    if not (math.isfinite(args.epsilon) and args.epsilon >= 0):
        parser.error("--epsilon must be a finite number >= 0 (metres)")
    available = _available_engines()
    names = list(available) if args.engines is None else [e.strip() for e in args.engines.split(",") if e.strip()]
    for name in names:
        if name not in available:
            parser.error(f"engine {name!r} is not available (available: {', '.join(available)})")
    wanted_scenes = None if args.scenes is None else {s.strip() for s in args.scenes.split(",") if s.strip()}
    server = stop = None
    url = None
    if args.seconds > 0:
        ctx = mp.get_context("spawn")
        stop = ctx.Event()
        parent, child = ctx.Pipe()
        server = ctx.Process(target=_serve, args=(child, stop), daemon=True)
        server.start()
        if not parent.poll(30):
            print("hapticproxy bench clients: the reference server did not start", file=sys.stderr)
            return 1
        url = parent.recv()
    rows = []
    try:
        for name in names:
            cls = available[name]
            scenes = [s for s in cls.scenes() if wanted_scenes is None or s in wanted_scenes]
            for scene in scenes:
                row = {"engine": name, "scene": scene}
                try:
                    engine = cls()
                    try:
                        row.update(time_ticks(engine, scene, ticks=args.ticks, warmup=args.warmup, repeat=args.repeat,
                                              epsilon_m=args.epsilon, max_contacts=args.max_contacts))
                    finally:
                        engine.close()
                    if url is not None:
                        row.update(sustained(cls, scene, url, seconds=args.seconds, epsilon_m=args.epsilon,
                                             max_contacts=args.max_contacts))
                    else:
                        row.update(sustained_hz=None, sent_hz=None)
                except Exception as exc:  # noqa: BLE001 - one broken engine must not hide the others' figures
                    print(f"hapticproxy bench clients: {name}/{scene} failed: {type(exc).__name__}: {exc}", file=sys.stderr)
                    continue
                rows.append(row)
                if not args.json:
                    print(f"{name:9s} {scene:8s} tick median {row['tick_median_us']:7.1f} us  p99 "
                          f"{row['tick_p99_us']:7.1f} us (cpu {row['tick_cpu_p99_us']:6.1f})  contacts mean {row['contacts_mean']:5.2f} max "
                          f"{row['contacts_max']:2d}  sustained {row['sustained_hz']} updates/s", flush=True)
    finally:
        if server is not None:
            stop.set()
            server.join(5)
            if server.is_alive():
                server.terminate()
    if args.json:
        print_json(rows)
    else:
        p99 = [r["tick_p99_us"] for r in rows]
        if p99:
            print(f"worst tick p99 {max(p99):.1f} us; median of medians "
                  f"{statistics.median(r['tick_median_us'] for r in rows):.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
