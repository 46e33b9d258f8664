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
import importlib.util
import os
from pathlib import Path

#: Modules holding the server's numba kernels (imported to find them).
SERVER_KERNEL_MODULES = (
    "hapticproxy.server.model.kernels",
    "hapticproxy.server.model.linkage",
    "hapticproxy.server.model.slot",
    "hapticproxy.server.safety",
    "hapticproxy.server.control",
    "hapticproxy.server.tick",
    "hapticproxy.server.loop",
    "hapticproxy.server.ingest",
    "hapticproxy.server.egress",
    "hapticproxy.server.prediction",
    "hapticproxy.server.rings",
    "hapticproxy.server.devices.dynamics",
    "hapticproxy.server.devices.hands",
    "hapticproxy.server.devices.mapping",
    "hapticproxy.server.passivity",
    "hapticproxy.server.devices.frozen",
)

#: Modules that define numba C callbacks (``@cfunc``, compiled when the module is imported, so
#: never imported from here): their caches are dropped by file name with the kernels' (the servo
#: callback runs the whole tick, and kept an older telemetry row's layout when it was not).
CFUNC_MODULES = ("hapticproxy.server.servo", "hapticproxy.server.devices.hd_native")


#: Modules of :data:`SERVER_KERNEL_MODULES` that import kernels but define none (glue: an edit
#: there changes no compiled code, so it must not cost a minute of compiling).
GLUE_MODULES = ("hapticproxy.server.loop",)

#: Every source file whose code ends up in a cached kernel, relative to the ``hapticproxy``
#: package root (server and client files alike: read as text, never imported from here). Numba
#: keys each kernel's cache on its own file only, so a kernel that inlines another module's
#: (``control.haptic_step`` calls ``model.kernels.step_rigid``) would keep running the old code
#: after an edit there; :func:`refresh_stale_caches` drops every cache when any of these changes.
#: The clients' narrow phase reads constants of ``clients/contacts.py`` too (its server-side
#: counterpart, the constants the server's kernels read, is :func:`kernel_constants`).
KERNEL_SOURCES = tuple(name.removeprefix("hapticproxy.").replace(".", "/") + ".py"
                       for name in SERVER_KERNEL_MODULES + CFUNC_MODULES if name not in GLUE_MODULES) + (
    "clients/narrowphase.py", "clients/geometry.py", "clients/contacts.py", "protocol/quaternion.py",
    "server/native.py")
_STAMP = "hapticproxy-kernel-sources.sha256"


def sources_digest() -> str:
    """One hash of every kernel source, of the constants the server's kernels read and of the
    numba that compiles them."""
    import hashlib

    import numba

    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256(numba.__version__.encode())
    for rel in KERNEL_SOURCES:
        f = root / rel
        h.update(rel.encode())
        h.update(f.read_bytes() if f.exists() else b"-")
    h.update(kernel_constants())
    return h.hexdigest()


def _frozen(v) -> bytes | None:
    """The bytes of a value numba would freeze into a kernel (a number, a string, a tuple or an
    array of them), or ``None`` for anything else (functions, modules, types)."""
    import numpy as np

    if v is None or isinstance(v, (bool, int, float, complex, str, bytes)):
        return repr(v).encode()
    if isinstance(v, np.generic):
        return repr(v.item()).encode()
    if isinstance(v, np.ndarray):
        return f"{v.dtype.str}{v.shape}".encode() + v.tobytes()
    if isinstance(v, tuple):
        parts = [_frozen(x) for x in v]
        return None if any(p is None for p in parts) else b"(" + b",".join(parts) + b")"
    return None


def kernel_constants(modules=SERVER_KERNEL_MODULES) -> bytes:
    """The value of every module-level constant the kernels of ``modules`` read, by name.

    Numba freezes a global's value into the compiled code, and its cache checks only the kernel's
    own file: a changed ``model/layout.py`` offset, protocol limit or controller id would
    otherwise keep running with the old value (seen: after ``K = 1`` -> ``K = 2`` in another
    file, a cached ``return K`` still returned 1). Values, not files: an edited docstring there
    recompiles nothing."""
    import types

    from numba.core.registry import CPUDispatcher

    found = {}
    for name in modules:  # every dispatcher, the inlined and the imported ones too (unlike dispatchers())
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        found.update((id(o), o) for o in vars(mod).values() if isinstance(o, CPUDispatcher))
    parts = []
    for d in sorted(found.values(), key=lambda d: (d.py_func.__module__, d.py_func.__qualname__)):
        f = d.py_func
        g = f.__globals__
        names, stack = set(), [f.__code__]
        while stack:
            co = stack.pop()
            names.update(co.co_names)
            stack.extend(c for c in co.co_consts if isinstance(c, types.CodeType))
        mods = [v for v in (g.get(n) for n in names) if isinstance(v, types.ModuleType)
                and v.__name__.startswith("hapticproxy.")]
        for name in sorted(names):
            for owner, v in [(f.__module__, g[name])] if name in g else [(m.__name__, getattr(m, name)) for m in mods
                                                                          if hasattr(m, name)]:
                b = _frozen(v)
                if b is not None:
                    parts.append(f"{f.__module__}.{f.__qualname__}:{owner}.{name}=".encode() + b)
    return b"\n".join(parts)


def refresh_stale_caches(modules=SERVER_KERNEL_MODULES) -> int:
    """Drop the cached kernels of ``modules`` compiled from other sources than today's (see
    :data:`KERNEL_SOURCES`); returns how many were dropped (they compile at the next warm-up)."""
    digest = sources_digest()
    by_dir: dict[str, list] = {}
    src_cache: dict[Path, str] = {}
    for d in dispatchers(modules):
        cache = getattr(d, "_cache", None)
        path = getattr(cache, "_cache_path", None)
        if path:
            by_dir.setdefault(path, []).append(d)
            src_cache[Path(d.py_func.__code__.co_filename).resolve().parent] = path
    cfunc_stems: dict[str, list] = {}
    for name in CFUNC_MODULES if modules is SERVER_KERNEL_MODULES or set(SERVER_KERNEL_MODULES) <= set(modules) else ():
        spec = importlib.util.find_spec(name)
        origin = Path(spec.origin).resolve() if spec is not None and spec.origin else None
        if origin is not None and origin.parent in src_cache:
            cfunc_stems.setdefault(src_cache[origin.parent], []).append(origin.stem)
    dropped = 0
    for path, ds in by_dir.items():
        stamp = Path(path) / _STAMP
        try:
            if stamp.read_text() == digest:
                continue
        except OSError:
            pass
        for d in ds:
            index = Path(d._cache._cache_file._index_path)
            for f in [index, *index.parent.glob(index.name[:-len(".nbi")] + ".*.nbc")]:
                try:
                    f.unlink()
                    dropped += f.suffix == ".nbi"
                except FileNotFoundError:
                    pass
        for stem in cfunc_stems.get(path, ()):
            for f in [*Path(path).glob(stem + ".*.nbi"), *Path(path).glob(stem + ".*.nbc")]:
                f.unlink(missing_ok=True)
                dropped += f.suffix == ".nbi"
        try:
            Path(path).mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest)
        except OSError:
            pass  # a read-only cache: numba falls back to compiling in memory
    return dropped


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
