"""The distribution installs and imports both ways: a wheel in a fresh virtual environment, and
the editable install the README's commands make."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUBPACKAGES = ["hapticproxy.protocol", "hapticproxy.server", "hapticproxy.server.model", "hapticproxy.clients",
               "hapticproxy.cli", "hapticproxy.benchmarks", "hapticproxy.experiments", "hapticproxy.testing"]


def _declared_packages() -> list[str]:
    import tomllib
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["tool"]["setuptools"]["packages"]


def test_every_package_folder_is_declared():
    declared = set(_declared_packages())
    assert set(SUBPACKAGES) <= declared
    mapping = {"protocol": "hapticproxy.protocol", "server": "hapticproxy.server", "clients": "hapticproxy.clients",
               "cli": "hapticproxy.cli", "benchmarks": "hapticproxy.benchmarks", "experiments": "hapticproxy.experiments",
               "testing": "hapticproxy.testing"}
    for folder, name in mapping.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            pkg = ".".join([name] + [p for p in rel.parts])
            assert pkg in declared, f"{init.parent} is a package but {pkg} is not in pyproject.toml"


def _import_check(python: str, cwd: Path) -> str:
    code = ("import importlib, json; mods = " + repr(SUBPACKAGES + ["hapticproxy.server.model.kernels"]) +
            "; print(json.dumps({m: importlib.import_module(m).__file__ for m in mods}))")
    out = subprocess.run([python, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_wheel_installs_and_imports_in_a_fresh_venv(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".venv", ".git", "out", "build", "dist", "*.egg-info",
                                                             "__pycache__", ".pytest_cache", ".hypothesis"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(wheels), str(src)], check=True, timeout=600, capture_output=True)
    (wheel,) = wheels.glob("hapticproxy-*.whl")
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = str(env_dir / "bin" / "python")
    purelib = subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    subprocess.run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", "-q", str(wheel)],
                   check=True, timeout=600, capture_output=True)
    # third-party dependencies come from the project's venv (a .pth is read only in site dirs,
    # so the editable install there stays invisible to this environment)
    Path(purelib, "_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    files = _import_check(py, tmp_path)
    for name in SUBPACKAGES:
        assert f'"{name}"' in files
    assert str(ROOT) not in files and purelib in files
    console = env_dir / "bin" / "hapticproxy"
    assert console.exists()
    out = subprocess.run([str(console), "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "demo" in out.stdout


def test_editable_install_imports_from_the_source_tree(tmp_path):
    files = json.loads(_import_check(sys.executable, tmp_path))
    # through .venv/static/'s folder links (what run.sh makes for static tools) or the editable
    # install's own hook: the files of this checkout either way
    assert Path(files["hapticproxy.protocol"]).resolve() == ROOT / "protocol" / "__init__.py"
    assert Path(files["hapticproxy.server.model.kernels"]).resolve() == ROOT / "server" / "model" / "kernels.py"
    assert os.path.exists(Path(sys.executable).parent / "hapticproxy")


def test_static_tools_resolve_the_namespace(tmp_path):
    """pylint (astroid: no import hooks, only the paths in sys.path) finds every package and
    a module of each, as pyright and an IDE do through the same plain path in a .pth file
    (``run.sh`` writes it: setuptools' editable install maps the folders by an import hook
    that static tools cannot follow)."""
    names = _declared_packages() + ["hapticproxy.server.loop", "hapticproxy.protocol.messages",
                                    "hapticproxy.clients.registry"]
    probe = tmp_path / "probe.py"
    probe.write_text('"""Imports every package of hapticproxy."""\n' + "".join(f"import {n}\n" for n in names)
                     + "print(" + ", ".join(names) + ")\n")
    out = subprocess.run([sys.executable, "-m", "pylint", "--disable=all", "--enable=import-error,no-name-in-module",
                          "--score=n", str(probe)], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
