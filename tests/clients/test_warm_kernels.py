"""The narrow phase's kernels (``hapticproxy.clients.narrowphase``, for ``hapticproxy warmup``):
``warm_up_kernels()`` compiles them with the one signature the pybullet engines then use, so
nothing compiles while an engine runs (a fresh interpreter, so nothing another test compiled
hides a signature the warm-up missed)."""
from __future__ import annotations

import json
import subprocess
import sys

SCRIPT = r"""
import json
import numpy as np
from numba.core.registry import CPUDispatcher
from hapticproxy.clients import narrowphase
from hapticproxy.clients.engine import ContactBuffer

def signatures():
    return {k: len(v.signatures) for k, v in vars(narrowphase).items()
            if isinstance(v, CPUDispatcher) and v.py_func.__module__ == narrowphase.__name__
            and v.targetoptions.get("inline") != "always"}

narrowphase.warm_up_kernels()
after_warm = signatures()
from hapticproxy.clients.pybullet_engine import PybulletEngine
from hapticproxy.clients.pybullet_linkage import PybulletLinkageEngine
for cls, scene, target in ((PybulletEngine, "peg", [0.0, 0.0, 0.02]), (PybulletEngine, "loose", [0.0, 0.15, 0.02]),
                           (PybulletLinkageEngine, "chain", [0.2, 0.0, 0.01])):
    e = cls()
    e.load_scene(scene)
    e.set_epsilon(0.005)
    buf = ContactBuffer(3)
    found = 0
    for k in range(400):
        pose = e.tool_pose(np.zeros(7)).copy()
        pose[:3] += 0.002 * (np.array(target) - pose[:3]) / max(1e-9, np.linalg.norm(np.array(target) - pose[:3]))
        e.drive_tool(pose, np.zeros(6), np.zeros(6))
        e.step(0.002)
        found = max(found, e.contacts_found)
        e.contacts(buf, 3)
    e.close()
    assert found > 3, (scene, found)  # clustering ran
print(json.dumps({"warm": after_warm, "run": signatures()}))
"""


def test_warm_up_compiles_every_kernel_with_the_one_signature_the_engines_use():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    # the kernels called from Python: one signature each (the helpers they call are compiled into
    # them, or loaded with them from the cache)
    assert got["warm"]["_contacts_kernel"] == 1 and got["warm"]["_guard_translation"] == 1, got["warm"]
    assert got["run"] == got["warm"]  # running the engines compiled nothing new
