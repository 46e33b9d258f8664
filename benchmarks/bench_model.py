"""``hapticproxy bench model``: cost of one haptic step of the local model, numba vs numpy.

For each tool kind (1dof, planar, spatial) and contact count (0, 8, 32, 64) it builds a caged
scene (contacts all around the proxy, separations within +-1 mm), pushes the proxy with a
rotating hand wrench, and replaces the contact set every 16 steps (an engine at ~60 Hz against
a 1 kHz loop) with half of the keys new, so the measured steps mix colliding (impulse) and
resting (penalty + friction) contact. The linkage rows (``linkage3``, ``linkage6``: spatial
chains of 3 and 6 revolute joints, held by the last link, d = 9 and 12, with the
velocity-product terms) spread their contacts over all links, at 8 and 32 contacts by default. Both implementations are timed on the same states in the
same run: the numba step as the server calls it (``LocalModel.step``), and the plain-numpy
reference step (``reference_step``). The garbage collector is off while timing, as in the loop.
Each update (``LocalModel.update``: the Python checks and the kernel) is timed too (median, p99):
half of its keys are new, so it exercises the re-key matching of every new key against the
contacts that left.

Prints a JSON list of rows (``--json``) or a table; the warm start (import + load of the cached
kernels in a fresh process) goes to stderr.
"""
from __future__ import annotations

import argparse
import gc
import math
import subprocess
import sys
import time

import numpy as np

from ..protocol.logs import doc_summary
from ..server.model import ContactParams, LinkSpec, LocalModel, ToolSpec
from ..server.model.reference import LinkageReference, reference_step
from ..protocol.jsonout import print_json

TOOLS = ("1dof", "planar", "spatial", "linkage3", "linkage6")
CONTACTS = (0, 8, 32, 64)
#: default contact counts of the linkage rows (the issue's: 8 and 32)
LINKAGE_CONTACTS = (8, 32)
UPDATE_EVERY = 16


def chain(joints: int) -> ToolSpec:
    """A spatial chain of ``joints`` revolute joints: 60 mm links of 80 g, joint axes alternating
    z, y, x, held by its last link."""
    inertia = (2.4e-5, 3.0e-5, 3.0e-5)
    axes = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0))
    links = [LinkSpec(0.08, (0.03, 0.0, 0.0), inertia)]
    for k in range(1, joints + 1):
        links.append(LinkSpec(0.08, (0.03, 0.0, 0.0), inertia, k - 1, "revolute", axes[k % 3], (0.06, 0.0, 0.0)))
    return ToolSpec.linkage(links, joints, planar=False)


def make_tool(kind: str) -> ToolSpec:
    if kind == "1dof":
        return ToolSpec.one_dof(0.5)
    if kind == "planar":
        return ToolSpec.planar(0.5, 1e-3, hand_point_m=(0.01, 0.0))
    if kind.startswith("linkage"):
        return chain(int(kind[len("linkage"):]))
    return ToolSpec.spatial(0.5, (1e-3, 1.5e-3, 2e-3), hand_point_m=(0.01, 0.0, 0.0))


def random_contacts(model: LocalModel, n: int, rng: np.random.Generator, key_base: int):
    """n contacts around the proxy's current pose, separations in [-1, 1] mm."""
    kind = model.tool.kind
    if kind == "1dof":
        nrm = np.zeros((n, 3))
        nrm[:, 0] = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    else:
        nrm = rng.normal(size=(n, 3))
        if kind == "planar":
            nrm[:, 2] = 0.0
        nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    Rs, cs = model.link_poses()
    links = rng.integers(0, len(Rs), size=n)
    # tool feature points on a 2 cm box around the COM (linkage: around each link's frame
    # origin, shifted half-way along the link), in the body frame
    body = rng.uniform(-0.01, 0.01, size=(n, 3))
    if kind == "1dof":
        body[:] = 0.0
    if kind == "planar":
        body[:, 2] = 0.0
    if kind.startswith("linkage"):
        body[:, 0] += 0.03
    feature_world = cs[links] + np.einsum("nij,nj->ni", Rs[links], body)
    d = rng.uniform(-1e-3, 1e-3, size=n)
    cp = feature_world - d[:, None] * nrm
    keys = np.zeros((n, 3), dtype=np.int64)
    keys[:, 0] = links
    keys[:, 1] = key_base + np.arange(n)
    return keys, cp, nrm, d, np.zeros(n)


def bench_row(kind: str, n: int, steps: int, numpy_steps: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    model = LocalModel(make_tool(kind), ContactParams(4000.0, 30.0, 0.0, 0.4, 0.3), period_s=1e-3, capacity=64)
    linkage = LinkageReference.of(model.tool) if model.is_linkage else None
    hand = np.zeros(model.hand_dim)
    numba_ns = np.empty(steps, dtype=np.int64)
    update_ns = []
    numpy_ns = []
    numpy_every = max(1, steps // max(numpy_steps, 1))
    collisions0 = 0
    resting = 0
    key_base = 0
    gc.collect()
    gc.disable()
    try:
        for i in range(steps):
            if n and i % UPDATE_EVERY == 0:
                # half of the keys survive, half are new: new contacts arrive as collisions
                key_base += n // 2
                cs = random_contacts(model, n, rng, key_base)
                t0 = time.perf_counter_ns()
                model.update(*cs)
                update_ns.append(time.perf_counter_ns() - t0)
            ang = 2 * math.pi * i / 500.0
            scale = 0.2 if linkage is not None else 1.0  # a 0.5 kg chain, not a 0.5 kg body
            hand[0] = 2.0 * scale * math.cos(ang)
            if model.hand_dim > 1:
                hand[1] = 2.0 * scale * math.sin(ang)
                hand[-1] = 0.01 * scale * math.sin(ang)
            if numpy_steps and i % numpy_every == 0 and len(numpy_ns) < numpy_steps:
                par, st, C, CI, cnt = model.arrays()
                t0 = time.perf_counter_ns()
                reference_step(model.kind, par, st, C, CI, cnt, hand, linkage=linkage)
                numpy_ns.append(time.perf_counter_ns() - t0)
            t0 = time.perf_counter_ns()
            model.step(hand)
            numba_ns[i] = time.perf_counter_ns() - t0
            if model.proxy_state == "resting":
                resting += 1
            if model.contact_count == 0 and n:
                collisions0 += 1
    finally:
        gc.enable()
    counters = model.counters()
    numba_med = float(np.median(numba_ns)) / 1e3
    numpy_med = float(np.median(numpy_ns)) / 1e3 if numpy_ns else float("nan")
    return {
        "tool": kind,
        "contacts": n,
        "numba_median_us": round(numba_med, 3),
        "numba_p99_us": round(float(np.percentile(numba_ns, 99)) / 1e3, 3),
        "numpy_median_us": round(numpy_med, 3),
        "speedup": round(numpy_med / numba_med, 1) if numpy_ns else None,
        "update_median_us": round(float(np.median(update_ns)) / 1e3, 3) if update_ns else None,
        "update_p99_us": round(float(np.percentile(update_ns, 99)) / 1e3, 3) if update_ns else None,
        "steps": steps,
        "numpy_steps": len(numpy_ns),
        "collision_steps": counters["collisions"],
        "resting_steps": resting,
        "nonfinite": counters["nonfinite"],
    }


def warm_start_s() -> float:
    """Import + load of every cached kernel in a fresh interpreter (the cache is warm by now)."""
    code = ("import time; t = time.perf_counter(); from hapticproxy.server.model import warm_up; "
            "warm_up(); print(time.perf_counter() - t)")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="hapticproxy bench model", description=doc_summary(__doc__))
    parser.add_argument("--json", action="store_true", help="print a JSON list of rows")
    parser.add_argument("--steps", type=int, default=20000, help="numba steps per row (default 20000)")
    parser.add_argument("--numpy-steps", type=int, default=400, help="numpy steps per row (default 400)")
    parser.add_argument("--tools", default=",".join(TOOLS), help="comma-separated tool kinds")
    parser.add_argument("--contacts", default=None,
                        help=f"comma-separated contact counts (default {','.join(map(str, CONTACTS))}; "
                             f"linkages {','.join(map(str, LINKAGE_CONTACTS))})")
    parser.add_argument("--seed", type=int, default=1, help="seed of the random contact sets (default 1)")
    args = parser.parse_args(argv)
    tools = [t for t in args.tools.split(",") if t]
    bad = [t for t in tools if t not in TOOLS]
    if bad or args.steps < 100 or args.numpy_steps < 0:
        print(f"hapticproxy bench model: tools must be among {TOOLS}; --steps >= 100; --numpy-steps >= 0",
              file=sys.stderr)
        return 2
    try:
        counts = None if args.contacts is None else [int(c) for c in args.contacts.split(",") if c]
    except ValueError:
        print("hapticproxy bench model: --contacts must be integers", file=sys.stderr)
        return 2

    def counts_of(kind):
        if counts is not None:
            return counts
        return LINKAGE_CONTACTS if kind.startswith("linkage") else CONTACTS

    rows = [bench_row(kind, n, args.steps, args.numpy_steps, args.seed) for kind in tools for n in counts_of(kind)]
    print(f"# warm start (fresh process: import + load cached kernels): {warm_start_s():.3f} s", file=sys.stderr)
    if args.json:
        print_json(rows, indent=1)
    else:
        print(f"{'tool':<9} {'contacts':>8} {'numba med':>10} {'numba p99':>10} {'numpy med':>10} {'speedup':>8} {'update':>8}")
        for r in rows:
            print(f"{r['tool']:<9} {r['contacts']:>8} {r['numba_median_us']:>9.2f}u {r['numba_p99_us']:>9.2f}u "
                  f"{r['numpy_median_us']:>9.1f}u {r['speedup'] or 0:>8.1f} {r['update_median_us'] or 0:>7.1f}u")
    return 0


if __name__ == "__main__":
    sys.exit(main())
