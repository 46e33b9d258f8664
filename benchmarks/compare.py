"""``python -m hapticproxy.benchmarks.compare --baseline DIR``: this tree's benchmarks against
another checkout's, in one run on one machine.

A restructure must not cost speed, and two benchmark runs an hour apart on a shared machine do
not say whether it did. This runs ``hapticproxy bench NAME --json`` of both trees alternately
(baseline, this tree, baseline, ...: ``--rounds`` each, so load that comes and goes hits both),
takes the median of every time figure (a field ending in ``_us``) per row, and prints both with
their ratio (this tree / baseline: below 1 is faster). Rows are matched by their text fields
(tool, message, engine, ...) and the ``contacts`` count.

``DIR`` is a checkout with its own ``.venv`` (e.g. ``git worktree add /tmp/base REV`` and
``sh /tmp/base/run.sh warmup``).
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

#: the benchmarks compared by default, with the arguments both trees get (short runs: the rounds
#: give the repetition)
BENCHES = {
    "model": ["--steps", "5000", "--numpy-steps", "20"],
    "codec": ["--repeats", "21"],
    "loop": ["--seconds", "20", "--naive-seconds", "5"],
    "clients": [],
}
_ID_INTS = ("contacts", "links", "n", "batch")
#: text fields that describe a run rather than name a row (the machine, the clock used)
_NOT_IDS = ("machine", "clock")


def _rows(out: str) -> list[dict]:
    """The rows of a bench's ``--json`` output: a JSON list, one object, or one object per line."""
    text = out.strip()
    try:
        doc = json.loads(text)
        docs = doc if isinstance(doc, list) else [doc]
    except json.JSONDecodeError:
        docs = [json.loads(line) for line in text.splitlines() if line.startswith("{")]
    rows = []
    for d in docs:
        if isinstance(d, dict) and isinstance(d.get("rows"), list):
            rows += [r for r in d["rows"] if isinstance(r, dict)]
        elif isinstance(d, dict):
            rows.append(d)
            # a report with row lists inside (bench loop's ``update_steps``): those rows too
            for v in d.values():
                if isinstance(v, list):
                    rows += [r for r in v if isinstance(r, dict)]
    return rows


def _label(row: dict) -> str:
    parts = [f"{k}={v}" for k, v in row.items() if isinstance(v, str) and len(v) < 60 and k not in _NOT_IDS]
    parts += [f"{k}={row[k]}" for k in _ID_INTS if isinstance(row.get(k), int)]
    return " ".join(parts) or "-"


def _times(rows: list[dict]) -> dict[tuple[str, str], float]:
    out: dict[tuple[str, str], float] = {}
    seen: dict[str, int] = {}
    for row in rows:
        label = _label(row)
        seen[label] = seen.get(label, 0) + 1
        if seen[label] > 1:
            label += f" #{seen[label]}"
        for k, v in row.items():
            if not k.endswith("_us"):
                continue
            # a figure, or a distribution of one ({"p50": ..., "p99": ...}: bench loop's)
            for fig, x in ([(k, v)] if not isinstance(v, dict) else [(f"{k}.{q}", x) for q, x in v.items() if q != "n"]):
                if isinstance(x, (int, float)) and not isinstance(x, bool):
                    out[(label, fig)] = float(x)
    return out


def run_bench(tree: Path, name: str, args: list[str], timeout_s: float) -> dict[tuple[str, str], float]:
    exe = tree / ".venv" / "bin" / "hapticproxy"
    p = subprocess.run([str(exe), "bench", name, "--json", *args], capture_output=True, text=True,
                       timeout=timeout_s, cwd=tree)
    if p.returncode != 0:
        raise RuntimeError(f"{exe} bench {name} exited {p.returncode}: {p.stderr.strip()[-400:]}")
    return _times(_rows(p.stdout))


def compare(baseline: Path, here: Path, names, rounds: int, timeout_s: float, log=print) -> list[dict]:
    rows = []
    for name in names:
        got: dict[str, list[dict]] = {"baseline": [], "this": []}
        for i in range(rounds):
            for which, tree in (("baseline", baseline), ("this", here)):
                log(f"bench {name}: {which} round {i + 1}/{rounds}", file=sys.stderr)
                got[which].append(run_bench(tree, name, BENCHES.get(name, []), timeout_s))
        keys = sorted(set().union(*got["baseline"]) & set().union(*got["this"]))
        for key in keys:
            b = statistics.median(r[key] for r in got["baseline"] if key in r)
            t = statistics.median(r[key] for r in got["this"] if key in r)
            rows.append({"bench": name, "row": key[0], "figure": key[1], "baseline_us": round(b, 3),
                         "this_us": round(t, 3), "ratio": round(t / b, 3) if b > 0 else None})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hapticproxy.benchmarks.compare", description=__doc__.split("\n\n")[0])
    p.add_argument("--baseline", required=True, type=Path, help="the other checkout (with its .venv)")
    p.add_argument("--benches", default=",".join(BENCHES), help="comma-separated (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="runs of each bench per tree (default 3)")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per bench run")
    p.add_argument("--json", action="store_true", help="one JSON object per row")
    a = p.parse_args(argv)
    here = Path(__file__).resolve().parents[1]
    if not (a.baseline / ".venv" / "bin" / "hapticproxy").exists():
        p.error(f"--baseline {a.baseline}: no .venv/bin/hapticproxy there")
    if a.rounds < 1:
        p.error("--rounds must be >= 1")
    try:
        rows = compare(a.baseline.resolve(), here, [n for n in a.benches.split(",") if n], a.rounds, a.timeout)
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        print(f"compare: {exc}", file=sys.stderr)
        return 1
    if a.json:
        for r in rows:
            print(json.dumps(r))
        return 0
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"this tree / baseline {a.baseline} (median of {a.rounds} alternating rounds)")
    for col, just in (("bench", "left"), ("row", "left"), ("figure", "left"), ("baseline us", "right"),
                      ("this us", "right"), ("ratio", "right")):
        table.add_column(col, justify=just)
    for r in rows:
        table.add_row(r["bench"], r["row"], r["figure"], f"{r['baseline_us']:.3f}", f"{r['this_us']:.3f}",
                      "-" if r["ratio"] is None else f"{r['ratio']:.2f}")
    Console(width=140).print(table)
    return 0

if __name__ == "__main__":
    sys.exit(main())
