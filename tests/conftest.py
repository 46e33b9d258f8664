"""Suite-wide: the test process's own garbage-collection pauses, said at the end of a run.

Tests that time real peers in threads of this process (the conformance kit, the transports)
see a collection as a stall of their own: the summary line says how long the longest was, so
a failure on a busy CI host can be weighed against it.
"""
from __future__ import annotations

import gc
import time

import pytest

_pauses = {"started": 0.0, "longest_s": 0.0, "longest_gen": -1, "over_100ms": 0, "count": 0}


def _on_gc(phase: str, info: dict) -> None:
    if phase == "start":
        _pauses["started"] = time.perf_counter()
        return
    took = time.perf_counter() - _pauses["started"]
    _pauses["count"] += 1
    if took > 0.1:
        _pauses["over_100ms"] += 1
    if took > _pauses["longest_s"]:
        _pauses["longest_s"] = took
        _pauses["longest_gen"] = info.get("generation", -1)


def pytest_configure(config) -> None:
    gc.callbacks.append(_on_gc)


def pytest_unconfigure(config) -> None:
    if _on_gc in gc.callbacks:
        gc.callbacks.remove(_on_gc)


def pytest_terminal_summary(terminalreporter) -> None:
    p = _pauses
    terminalreporter.write_line(
        f"garbage collection in the test process: {p['count']} collections, the longest "
        f"{p['longest_s'] * 1e3:.0f} ms (generation {p['longest_gen']}), {p['over_100ms']} over 100 ms; "
        f"{len(gc.get_objects())} objects tracked at the end")


@pytest.fixture
def frozen_gc():
    """No garbage collection of what earlier tests left (this process's older objects are
    frozen, as the loop process freezes its own) while a test times peers in threads of this
    process: such a collection took up to 165 ms here in a run of tests/server and tests/faults."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
