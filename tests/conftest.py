"""Suite-wide: no full garbage collection inside a test.

Tests that time real peers in threads of this process (the conformance kits, the transports,
clients against the server) see a collection as a stall of their own. A full one scans every
object earlier tests left: in one CI run of the whole suite the longest took 463 ms and 48 took
over 100 ms, longer than the 0.5 s silence timeout some tests grant once added to a busy host's
own hiccups. So the oldest generation is not collected automatically; a full collection runs
between tests, every ``_FULL_EVERY`` tests (the loop process does the same in its own way: it
freezes what it built and disables the collector). The summary line says what collections cost
inside tests and between them.
"""
from __future__ import annotations

import gc
import time

_FULL_EVERY = 20

_stats = {"started": 0.0, "between": False, "n": 0, "longest_s": 0.0, "longest_gen": -1, "over_100ms": 0,
          "full_n": 0, "full_longest_s": 0.0, "tests": 0, "threshold": None}


def _on_gc(phase: str, info: dict) -> None:
    if phase == "start":
        _stats["started"] = time.perf_counter()
        return
    took = time.perf_counter() - _stats["started"]
    if _stats["between"]:
        _stats["full_n"] += 1
        _stats["full_longest_s"] = max(_stats["full_longest_s"], took)
        return
    _stats["n"] += 1
    if took > 0.1:
        _stats["over_100ms"] += 1
    if took > _stats["longest_s"]:
        _stats["longest_s"] = took
        _stats["longest_gen"] = info.get("generation", -1)


def pytest_configure(config) -> None:
    gc.callbacks.append(_on_gc)
    _stats["threshold"] = gc.get_threshold()
    t0, t1, _ = _stats["threshold"]
    gc.set_threshold(t0, t1, 1_000_000)  # the oldest generation: only between tests (below)


def pytest_runtest_logfinish(nodeid, location) -> None:
    _stats["tests"] += 1
    if _stats["tests"] % _FULL_EVERY == 0:
        _stats["between"] = True
        try:
            gc.collect()
        finally:
            _stats["between"] = False


def pytest_unconfigure(config) -> None:
    if _on_gc in gc.callbacks:
        gc.callbacks.remove(_on_gc)
    if _stats["threshold"] is not None:
        gc.set_threshold(*_stats["threshold"])


def pytest_terminal_summary(terminalreporter) -> None:
    s = _stats
    terminalreporter.write_line(
        f"garbage collection inside tests: {s['n']} collections, the longest {s['longest_s'] * 1e3:.0f} ms "
        f"(generation {s['longest_gen']}), {s['over_100ms']} over 100 ms; between tests: {s['full_n']} full "
        f"collections, the longest {s['full_longest_s'] * 1e3:.0f} ms; {len(gc.get_objects())} objects tracked "
        f"at the end")
