"""``hapticproxy warmup``: compile (or load from numba's cache) every kernel of the server and of
the installed engines before anything runs (set-up runs it; see ``server/warm.py`` for why)."""
from __future__ import annotations

import argparse
import importlib
import logging
import sys
import time

from ..protocol.logs import doc_summary
from ..protocol import logs
from ..server import config as cfgmod
from ..server.loop import HapticLoop
from ..server.warm import SERVER_KERNEL_MODULES, cold, dispatchers, refresh_stale_caches

#: engine modules with numba kernels, each with a ``warm_up_kernels()``; skipped when the
#: engines extra is not installed
CLIENT_KERNEL_MODULES = ("hapticproxy.clients.narrowphase",)


def _settings(device_kind: str, tool: str = ""):
    return cfgmod.load({"transport": {"url": f"mem://warmup-{device_kind}-{tool or device_kind}"},
                        "model": {"tool": tool}, "device": {"driver": "sim", "kind": device_kind},
                        "telemetry": {"ring_s": 0.1}})


def warm_server() -> int:
    """Warm a loop for every device kind and tool kind; returns how many loops were warmed."""
    n = 0
    for device_kind, tool in (("1dof", ""), ("planar", ""), ("spatial", ""), ("planar", "linkage"),
                              ("spatial", "linkage")):
        loop = HapticLoop.build(_settings(device_kind, tool))
        try:
            loop.warm_up()
            n += 1
        finally:
            loop.close()
    from ..server.devices import mapping

    mapping.warm_up()  # the workspace mapping's kernels (a device with a [device] mapping runs them)
    return n


def warm_clients() -> list[str]:
    done = []
    for name in CLIENT_KERNEL_MODULES:
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        mod.warm_up_kernels()
        done.append(name.rsplit(".", 1)[-1])
    return done


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy warmup", description=doc_summary(__doc__))
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing when every kernel is cached")
    args = p.parse_args(argv)
    logs.configure(logging.INFO)
    log = logging.getLogger("hapticproxy.warmup")
    modules = SERVER_KERNEL_MODULES + CLIENT_KERNEL_MODULES
    t0 = time.monotonic()
    refresh_stale_caches(modules)  # kernels compiled from older sources would run the old code
    todo = cold(modules)
    if todo:
        total = len(dispatchers(modules))
        why = ("first run on this machine: a few minutes on 2 cores" if len(todo) == total
               else f"{total - len(todo)} already cached; these changed or no start needed"
                  " them yet")
        log.info("compiling %d kernels (%s) ...", len(todo), why)
    loops = warm_server()
    engines = warm_clients()
    left = cold(modules)
    if todo or not args.quiet:
        what = f"{loops} loop configurations" + (f" and the engines' {', '.join(engines)}" if engines else "")
        log.info("kernels ready: %d (%d compiled now; %s) in %.1f s", len(dispatchers(modules)), len(todo) - len(left),
                 what, time.monotonic() - t0)
    if left:
        log.warning("not cached after warm-up (they compile at first use): %s", ", ".join(left))
    return 0


if __name__ == "__main__":
    sys.exit(main())
