"""``hapticproxy bench recorder``: does the MCAP recorder keep up, and does it cost the loop?

One run of the real server (supervisor + loop process) at ``--rate`` (default 4 kHz, the
``accurate`` preset: 64 contacts), a client on UDP loopback sending a full contact set (64
contacts, all within epsilon) at 60 Hz, the simulated planar device pushed by a 0.5 N hand.
The run alternates ``--phases`` windows of ``--seconds`` without and with recording (the same
loop, the same client; statistics reset at each window's start), so both see the same machine.

Per window it reports the loop's wake-up lateness and step compute percentiles (1 us bins,
upper edges) and missed deadlines; for the recording windows also the rows recorded against the
rows the loop wrote, rows lost (overwritten in the ring before they were copied: must be 0),
contact updates recorded, the supervisor's CPU time spent draining per second of recording
(``drain_cpu_fraction``: it runs in the supervisor, not in the loop) and the file size. Prints
a table and, with ``--json``, one JSON object.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time

import numpy as np

from ..protocol.logs import doc_summary
from .bench_loop import floor_client, free_port
from ..protocol.codec import Hello
from ..protocol.messages import ToolKind
from ..server import config as cfgmod
from ..server.daemon import Supervisor
from ..protocol.jsonout import print_json


def _client(url: str, stop: threading.Event, rate_hz: float, n_contacts: int, counts: dict) -> None:
    """A floor under a planar box tool that follows the proxy, reported as ``n_contacts`` points
    along the box's bottom edge (all within epsilon: the full set every update)."""
    hello = Hello(client_nonce=1, engine="bench-recorder floor", tool_kind=ToolKind.PLANAR, mass_kg=0.2,
                  inertia_kg_m2=(2e-4, 2e-4, 2e-4, 0, 0, 0), max_contacts=n_contacts, epsilon_m=0.005,
                  env_rate_hz=rate_hz)
    keys = np.column_stack([np.zeros(n_contacts), np.ones(n_contacts), np.arange(n_contacts)]).astype(np.int64)
    nrm = np.tile([0.0, 1.0, 0.0], (n_contacts, 1))
    bx = np.linspace(-0.02, 0.02, n_contacts)

    def contacts(pose, c, s):
        x = pose[0] + c * bx + s * 0.01
        y = pose[1] + s * bx - c * 0.01
        cp = np.column_stack([x, np.zeros(n_contacts), np.zeros(n_contacts)])
        d = np.clip(y, -0.002, 0.004)  # within epsilon (5 mm): every point is a contact
        return keys, cp, nrm, d

    floor_client(url, stop, rate_hz, hello, np.array([0.0, 0.011, 0.0, 1.0, 0.0, 0.0, 0.0]), contacts, counts)


def run(rate_hz: float, seconds: float, phases: int, n_contacts: int) -> dict:
    settings = cfgmod.load({
        "preset": "accurate",
        "loop": {"rate_hz": rate_hz},
        "model": {"capacity": n_contacts},
        "transport": {"url": f"udp://127.0.0.1:{free_port()}"},
        "status": {"address": f"127.0.0.1:{free_port()}"},
        "device": {"driver": "sim", "kind": "planar", "hand": {"type": "constant", "wrench": [0.0, -0.5, 0.0]}},
        "telemetry": {"ring_s": 2.0},
    })
    sup = Supervisor(settings)
    stop = threading.Event()
    counts = {"updates_sent": 0, "proxy_states": 0}
    th = None
    tmp = tempfile.TemporaryDirectory(prefix="hp-bench-recorder-")
    windows = []
    try:
        sup.start()
        th = threading.Thread(target=_client, args=(settings["transport"]["url"], stop, 60.0, n_contacts, counts),
                              daemon=True)
        th.start()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 2.0 or sup.shared.get("contacts") < n_contacts:
            sup._serve_status(0.05)
            sup.service()
            if time.monotonic() - t0 > 60:
                raise RuntimeError("the client never engaged with a full contact set")
        for k in range(2 * phases):
            recording = k % 2 == 1
            path = os.path.join(tmp.name, f"w{k}.mcap")
            sup.shared.request("reset_stats")
            time.sleep(0.05)  # the loop acknowledges within 10 ms
            if recording:
                sup.start_recording(path)
            drain_cpu = 0.0
            t1 = time.monotonic()
            while time.monotonic() - t1 < seconds:
                sup._serve_status(0.05)
                c0 = time.thread_time()
                sup.service()
                drain_cpu += time.thread_time() - c0
            snap = sup.shared.snapshot()
            wall = time.monotonic() - t1
            w = {"recording": recording, "seconds": round(wall, 2),
                 "lateness_us": {q: snap["lateness_us"][q] for q in ("p50", "p99", "p999", "max")},
                 "compute_us": {q: snap["compute_us"][q] for q in ("p50", "p99", "p999", "max")},
                 "missed_deadlines": snap["missed_deadlines"], "overruns": snap["overruns"],
                 "steps": snap["lateness_us"]["count"], "contacts": snap["contacts"]}
            if recording:
                wr = sup.writer
                c0 = time.thread_time()
                wr.drain(sup.shared)
                wr.close()
                drain_cpu += time.thread_time() - c0
                # what the loop wrote from the recording's first row to its last drain
                w.update(rows_loop=wr._read - wr.start_row, rows_recorded=wr.rows_written,
                         rows_lost=wr.rows_lost, updates_loop=wr._contact_seq - wr.start_contact,
                         updates_recorded=wr.contacts_written, contacts_lost=wr.contacts_lost,
                         drain_cpu_fraction=round(drain_cpu / wall, 4),
                         drain_us_per_row=round(drain_cpu / max(1, wr.rows_written) * 1e6, 2),
                         file_bytes=os.path.getsize(path))
                sup.writer = None
                sup.record = ""
                os.unlink(path)
            else:
                w["service_cpu_fraction"] = round(drain_cpu / wall, 4)
            windows.append(w)
    finally:
        stop.set()
        if th is not None:
            th.join(5)
        sup.close()
        tmp.cleanup()

    def agg(rec: bool, part: str, q: str):
        vals = [w[part][q] for w in windows if w["recording"] == rec and w[part][q] is not None]
        return max(vals) if vals else None

    return {"rate_hz": rate_hz, "contacts": n_contacts, "seconds_per_window": seconds, "windows": windows,
            "worst_without": {p: {q: agg(False, p, q) for q in ("p99", "p999", "max")} for p in ("lateness_us", "compute_us")},
            "worst_with": {p: {q: agg(True, p, q) for q in ("p99", "p999", "max")} for p in ("lateness_us", "compute_us")},
            "rows_lost": sum(w.get("rows_lost", 0) for w in windows),
            "keeps_up": all(w["rows_lost"] == 0 and w["rows_recorded"] == w["rows_loop"] for w in windows if w["recording"]),
            "rt_scheduling": bool(sup.shared.get("rt_scheduling")) if sup.shared.status is not None else None}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy bench recorder", description=doc_summary(__doc__))
    p.add_argument("--rate", type=float, default=4000.0, help="haptic rate [Hz] (default 4000)")
    p.add_argument("--seconds", type=float, default=10.0, help="seconds per window (default 10)")
    p.add_argument("--phases", type=int, default=2, help="pairs of windows without / with recording (default 2)")
    p.add_argument("--contacts", type=int, default=64, help="contacts per update (default 64, the most granted)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    args = p.parse_args(argv)
    try:
        res = run(args.rate, args.seconds, args.phases, args.contacts)
    except RuntimeError as exc:
        print(f"hapticproxy bench recorder: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print_json(res, indent=1)
        return 0
    print(f"recorder at {res['rate_hz']:g} Hz, {res['contacts']} contacts per update at 60 Hz, "
          f"{res['seconds_per_window']:g} s windows")
    print(f"{'window':>8} {'record':>6} {'late p50/p99/p99.9/max us':>28} {'compute p50/p99/p99.9/max us':>30} "
          f"{'missed':>6} {'rows loop/rec/lost':>20} {'updates loop/rec':>17} {'drain cpu':>9} {'us/row':>7}")
    for i, w in enumerate(res["windows"]):
        lat = "/".join(str(w["lateness_us"][q]) for q in ("p50", "p99", "p999", "max"))
        comp = "/".join(str(w["compute_us"][q]) for q in ("p50", "p99", "p999", "max"))
        rows = f"{w['rows_loop']}/{w['rows_recorded']}/{w['rows_lost']}" if w["recording"] else "-"
        upd = f"{w['updates_loop']}/{w['updates_recorded']}" if w["recording"] else "-"
        cpu = f"{w['drain_cpu_fraction'] * 100:.1f} %" if w["recording"] else f"{w['service_cpu_fraction'] * 100:.1f} %"
        per = f"{w['drain_us_per_row']:.1f}" if w["recording"] else "-"
        print(f"{i:>8} {'yes' if w['recording'] else 'no':>6} {lat:>28} {comp:>30} {w['missed_deadlines']:>6} "
              f"{rows:>20} {upd:>17} {cpu:>9} {per:>7}")
    print(f"keeps up: {'yes' if res['keeps_up'] else 'NO'} (rows lost {res['rows_lost']}); worst p99 lateness "
          f"without / with recording: {res['worst_without']['lateness_us']['p99']} / "
          f"{res['worst_with']['lateness_us']['p99']} us; compute p99 {res['worst_without']['compute_us']['p99']} / "
          f"{res['worst_with']['compute_us']['p99']} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
