"""Suite-wide: kernels compiled from today's sources, and no full garbage collection inside a test.

Numba keys a kernel's cache on its own file only: a kernel that inlines another module's code
(``inline="always"``, or any call into another file's kernel) keeps running the machine code it
was compiled with after an edit there (the review saw 28 of 28 tests pass on a changed inlined
kernel). ``run.sh``, ``hapticproxy warmup`` and the daemon drop such stale caches
(``server/warm.py``: ``refresh_stale_caches``); the test session does the same before anything is
collected (``pytest_configure``), so ``python -m pytest`` tests the code in the tree
(``tests/test_stale_kernels.py`` shows it on a temporary copy).


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

import pytest

_DROPPED = pytest.StashKey[int]()

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


def refresh_kernel_caches() -> int:
    """Drop every cached kernel compiled from other sources than today's (the server's and the
    engines' kernel modules, as ``hapticproxy warmup`` does); returns how many were dropped."""
    from hapticproxy.cli.warmup import CLIENT_KERNEL_MODULES
    from hapticproxy.server.warm import SERVER_KERNEL_MODULES, refresh_stale_caches

    return refresh_stale_caches(SERVER_KERNEL_MODULES + CLIENT_KERNEL_MODULES)


def pytest_configure(config) -> None:
    dropped = refresh_kernel_caches()
    if dropped:
        config.stash[_DROPPED] = dropped
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


def pytest_terminal_summary(terminalreporter, config) -> None:
    dropped = config.stash.get(_DROPPED, 0)
    if dropped:
        terminalreporter.write_line(f"kernel caches compiled from older sources dropped at the start: {dropped} "
                                    f"(they compiled again when first called)")
    s = _stats
    terminalreporter.write_line(
        f"garbage collection inside tests: {s['n']} collections, the longest {s['longest_s'] * 1e3:.0f} ms "
        f"(generation {s['longest_gen']}), {s['over_100ms']} over 100 ms; between tests: {s['full_n']} full "
        f"collections, the longest {s['full_longest_s'] * 1e3:.0f} ms; {len(gc.get_objects())} objects tracked "
        f"at the end")
