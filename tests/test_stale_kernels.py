"""The test session runs today's kernels: after an edit to a kernel that another file's kernel
inlines, ``python -m pytest`` with this suite's ``conftest.py`` runs the edited code, where the
same session without it runs the machine code numba cached before the edit.

On a temporary copy of ``protocol/`` and ``server/`` (its own ``NUMBA_CACHE_DIR``, nothing of
this tree's caches touched): ``server/model/kernels.py``'s ``_rigid_pose`` inlines
``protocol/quaternion.py``'s ``quat_to_matrix_into`` (``inline="always"``); it is compiled into
the cache, then the quaternion convention is edited (the matrix transposed). A probe test
compares the kernel's rotation with the Python function's: run with ``--noconftest`` it sees the
stale machine code (they differ), run with the suite's ``conftest.py`` it sees the edit."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = '''
import numpy as np
from hapticproxy.protocol import quaternion
from hapticproxy.server.model import kernels as k
from hapticproxy.server.model.layout import NPAR, NSTATE, S_Q, TOOL_SPATIAL


def test_the_kernel_runs_the_quaternion_convention_in_the_tree():
    assert quaternion.__file__.startswith({tmp!r}) and k.__file__.startswith({tmp!r})
    st = np.zeros(NSTATE)
    st[S_Q + 3:S_Q + 7] = (0.8, 0.0, 0.0, 0.6)  # 73.7 deg about z
    R = np.zeros((3, 3))
    k._rigid_pose(TOOL_SPATIAL, np.zeros(NPAR), st, R, np.zeros(3))
    want = quaternion.quat_to_matrix_into(st[S_Q + 3:S_Q + 7], np.zeros((3, 3)))
    assert np.allclose(R, want), (R, want)
'''


def _run(args, env, cwd):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=900, env=env, cwd=cwd)


def test_the_session_drops_a_kernel_cache_that_inlines_an_edited_kernel(tmp_path):
    pkg = tmp_path / "hapticproxy"
    for name in ("protocol", "server"):
        shutil.copytree(ROOT / name, pkg / name, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    tests = tmp_path / "tests"
    tests.mkdir()
    shutil.copy(ROOT / "tests" / "conftest.py", tests / "conftest.py")
    (tests / "test_probe.py").write_text(PROBE.format(tmp=str(tmp_path)))
    env = dict(os.environ, PYTHONPATH=str(tmp_path), NUMBA_CACHE_DIR=str(tmp_path / "numba"),
               PYTHONDONTWRITEBYTECODE="1")
    pytest_args = ["-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(tests), str(tests / "test_probe.py")]

    # today's sources: the probe passes and the kernel is now in the cache (stamped as current)
    first = _run(pytest_args, env, tmp_path)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    assert list((tmp_path / "numba").rglob("*_rigid_pose*.nbi")), "the kernel was not cached"

    # the inlined kernel's source changes (the rotation transposed); kernels.py does not
    q = pkg / "protocol" / "quaternion.py"
    src = q.read_text()
    edited = src.replace("2.0 * (x * y - z * w)", "2.0 * (x * y + z * w)", 1).replace(
        "R[1, 0] = 2.0 * (x * y + z * w)", "R[1, 0] = 2.0 * (x * y - z * w)", 1)
    assert edited != src
    q.write_text(edited)

    # without the suite's conftest: numba's cache of kernels.py is still valid by its own file,
    # so the session runs the old machine code
    stale = _run([*pytest_args, "--noconftest"], env, tmp_path)
    assert stale.returncode == 1 and "allclose" in stale.stdout, stale.stdout[-3000:] + stale.stderr[-3000:]

    # with it: the stale cache is dropped before anything runs, the kernel compiles from the edit
    fresh = _run(pytest_args, env, tmp_path)
    assert fresh.returncode == 0, fresh.stdout[-3000:] + fresh.stderr[-3000:]
    assert "kernel caches compiled from older sources dropped at the start" in fresh.stdout


def test_every_module_with_kernels_or_c_callbacks_is_refreshed():
    """A module that defines a cached kernel or C callback and is missing from
    ``SERVER_KERNEL_MODULES`` keeps stale machine code after an edit elsewhere (the Touch's servo
    callback once ran an older telemetry row's layout: its module was not listed)."""
    import re

    from hapticproxy.server import servo, warm

    root = Path(__file__).resolve().parent.parent
    defining = {
        "hapticproxy." + str(p.relative_to(root).with_suffix("")).replace("/", ".")
        for p in (root / "server").rglob("*.py")
        if re.search(r"^@(njit|cfunc)\b", p.read_text(), re.M)
    }
    listed = set(warm.SERVER_KERNEL_MODULES) | set(warm.CFUNC_MODULES)
    assert defining <= listed, sorted(defining - listed)
    # a stale stamp drops the servo callback's cache too (by its file's name: never imported here)
    index = Path(servo._servo_callback._cache._cache_file._index_path)
    assert index.exists()
    stamp = index.parent / warm._STAMP
    stamp.write_text("stale")
    warm.refresh_stale_caches()
    assert not index.exists()
