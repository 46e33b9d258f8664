"""Nothing compiles once the loop is armed: ``HapticLoop.warm_up`` covers every kernel signature
the loop calls in every state, for every device and tool kind (a compile inside the loop is a
stall of seconds that trips the device's watchdog: the first start on a fresh machine faulted
this way). Each kind runs in a fresh interpreter, so nothing another test compiled can hide a
signature warm-up missed; ``hapticproxy warmup`` is what set-up runs."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.mark.parametrize("kind", ["1dof", "planar", "spatial", "linkage", "planar-watchdog"])
def test_no_kernel_compiles_after_warm_up_in_any_state(kind):
    out = subprocess.run([sys.executable, str(HERE / "warm_probe.py"), kind], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["visited"] == ["engaged", "fading", "fault", "idle", "stopped", "stopping"], res
    assert res["state"] == "stopped"
    assert res["after_warm_up"] == 0, res
    assert res["late_compiles"] == 0, res


def test_warmup_command_leaves_nothing_cold():
    from hapticproxy.server.warm import SERVER_KERNEL_MODULES, cold

    out = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "warmup"], capture_output=True, text=True,
                         timeout=900)
    assert out.returncode == 0, out.stderr
    assert "kernels ready" in out.stderr
    assert cold(SERVER_KERNEL_MODULES) == []


def test_a_changed_kernel_source_drops_every_cached_kernel(tmp_path):
    """Numba keys a kernel's cache on its own file only: a kernel inlining another module's code
    would keep the old code after an edit there. A changed source digest drops them all."""
    import os

    code = ("import json, pathlib\n"
            "from hapticproxy.server import warm\n"
            "stamps = lambda: sorted(pathlib.Path(d._cache._cache_path) / warm._STAMP for d in warm.dispatchers())\n"
            "from hapticproxy.server import control\n"
            "first = warm.refresh_stale_caches()\n"
            "control._wrap(0.5)  # one small kernel compiled into the cache\n"
            "index = pathlib.Path(control._wrap._cache._cache_file._index_path)\n"
            "again = warm.refresh_stale_caches()\n"
            "kept = index.exists()\n"
            "for s in set(stamps()): s.write_text('an older source')\n"
            "dropped = warm.refresh_stale_caches()\n"
            "print(json.dumps({'again': again, 'kept': kept, 'dropped': dropped, 'gone': not index.exists()}))\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["again"] == 0 and res["kept"]    # today's sources: nothing dropped
    assert res["dropped"] >= 1 and res["gone"]  # an older source: the cached kernel is gone


@pytest.mark.parametrize("tool, counted", [("", ["step_other"]), ("linkage", ["haptic_step_linkage", "step_other"])])
def test_the_start_up_message_counts_only_what_this_loop_compiles(monkeypatch, tool, counted):
    """A rigid tool's loop never calls the linkage step: its missing cache must not make every
    start say it is compiling."""
    sys.path.insert(0, str(HERE))
    from server_harness import make_settings

    from hapticproxy.server import warm
    from hapticproxy.server.clock import SimClock
    from hapticproxy.server.devices.base import load_device
    from hapticproxy.server.loop import HapticLoop

    clock = SimClock(start_ns=1_000_000_000)
    settings = make_settings(device={"driver": "sim", "kind": "planar"}, model={"tool": tool})
    dev = load_device("sim", dict(settings["device"]), period_s=1e-3, clock_ns=clock.now_ns)
    loop = HapticLoop.build(settings, clock=clock, device=dev)
    try:
        monkeypatch.setattr(warm, "cold", lambda modules=warm.SERVER_KERNEL_MODULES: ["haptic_step_linkage", "step_other"])
        assert loop.cold_kernels() == counted
    finally:
        loop.close()


def test_a_changed_constant_of_another_file_changes_the_digest(monkeypatch):
    """Numba freezes a global's value into the kernel and checks only the kernel's own file: a
    changed offset in model/layout.py must drop the cached kernels that read it."""
    from hapticproxy.server import warm
    from hapticproxy.server.model import kernels

    before = warm.sources_digest()
    monkeypatch.setattr(kernels, "C_N", kernels.C_N + 1)  # as a new layout.py would bind it
    assert warm.sources_digest() != before
    monkeypatch.undo()
    assert warm.sources_digest() == before


def test_glue_modules_define_no_kernels_and_the_others_do():
    """An edit to glue (the loop) recompiles nothing; every other listed module holds kernels."""
    import importlib

    from numba.core.registry import CPUDispatcher

    from hapticproxy.server import warm

    for name in warm.SERVER_KERNEL_MODULES:
        mod = importlib.import_module(name)
        own = [o for o in vars(mod).values() if isinstance(o, CPUDispatcher) and o.py_func.__module__ == name]
        assert bool(own) == (name not in warm.GLUE_MODULES), name
    assert "server/loop.py" not in warm.KERNEL_SOURCES
