"""Compile (or load from numba's on-disk cache) every kernel before anything runs.

A kernel compiles the first time it is called with a new signature, which takes seconds: inside
the haptic loop that is a stall that trips the device's watchdog. So every process that runs a
deadline compiles first: the loop process runs ``HapticLoop.warm_up`` before it arms anything,
and set-up (``sh run.sh``, the container build) runs ``hapticproxy warmup`` once, so that even
the first start on a new machine only loads kernels from the cache.

``hapticproxy warmup`` (``cli/warmup.py``) builds a loop for every device and tool kind on an
in-memory transport and warms it (exactly the calls the loop makes, with the argument types it
passes), then the engines' own kernels; it prints what it did. Numba writes its cache next to the sources (``__pycache__``)
or under ``NUMBA_CACHE_DIR`` when that is set (the systemd unit and the container set it to a
directory the service user owns).
"""
from __future__ import annotations

import importlib
import os

#: Modules holding the server's numba kernels (imported to find them).
SERVER_KERNEL_MODULES = (
    "hapticproxy.server.model.kernels",
    "hapticproxy.server.model.linkage",
    "hapticproxy.server.control",
    "hapticproxy.server.loop",
    "hapticproxy.server.rings",
    "hapticproxy.server.devices.dynamics",
    "hapticproxy.server.devices.hands",
)


def dispatchers(modules=SERVER_KERNEL_MODULES) -> list:
    """The numba dispatchers defined in ``modules`` (each imported)."""
    from numba.core.registry import CPUDispatcher

    out = []
    for name in modules:
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        for obj in vars(mod).values():
            if (isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name
                    and obj.targetoptions.get("inline") != "always"):  # inlined: never compiled alone
                out.append(obj)
    return out


def cold(modules=SERVER_KERNEL_MODULES) -> list[str]:
    """Names of kernels with nothing in numba's cache yet (their first call compiles)."""
    names = []
    for d in dispatchers(modules):
        try:
            path = d._cache._cache_file._index_path
        except AttributeError:  # not a caching dispatcher: it compiles every time
            names.append(d.py_func.__qualname__)
            continue
        if not os.path.exists(path):
            names.append(d.py_func.__qualname__)
    return names


def _settings(device_kind: str, tool: str = ""):
    from . import config as cfgmod

    return cfgmod.load({"transport": {"url": f"mem://warmup-{device_kind}-{tool or device_kind}"},
                        "model": {"tool": tool}, "device": {"driver": "sim", "kind": device_kind},
                        "telemetry": {"ring_s": 0.1}})


def warm_server() -> int:
    """Warm a loop for every device kind and tool kind; returns how many loops were warmed."""
    from .loop import HapticLoop

    n = 0
    for device_kind, tool in (("1dof", ""), ("planar", ""), ("spatial", ""), ("planar", "linkage"),
                              ("spatial", "linkage")):
        loop = HapticLoop.build(_settings(device_kind, tool))
        try:
            loop.warm_up()
            n += 1
        finally:
            loop.close()
    return n
