"""Dependency direction: protocol imports only the standard library, numpy, msgpack and msgspec; server
and clients import protocol and never each other."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"protocol": "hapticproxy.protocol", "server": "hapticproxy.server", "clients": "hapticproxy.clients"}
STDLIB = set(sys.stdlib_module_names) | {"__future__"}
#: The one optional third-party import of the protocol package: the Zenoh backend, imported
#: lazily inside its own module.
PROTOCOL_EXTRA = {"zenoh": "transport/zenoh"}


def imports_of(source: str, module: str, is_package: bool) -> set[str]:
    """Absolute names of everything a module imports (relative imports resolved)."""
    tree = ast.parse(source)
    base = module.split(".") if is_package else module.split(".")[:-1]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parent = base[: len(base) - (node.level - 1)]
                name = ".".join(parent + ([node.module] if node.module else []))
                if node.module is None:
                    out.update(f"{name}.{a.name}" for a in node.names)
                    continue
            else:
                name = node.module or ""
            out.add(name)
    return out


def violations(folder: str, files: dict[str, str]) -> list[str]:
    """files: path relative to the folder -> source. Returns the offending imports."""
    pkg = PACKAGES[folder]
    bad = []
    for rel, source in files.items():
        parts = rel[:-3].split("/")
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        module = ".".join([pkg] + parts)
        for name in sorted(imports_of(source, module, is_package)):
            top = name.split(".")[0]
            if folder == "protocol":
                if top in STDLIB or top in ("numpy", "msgpack", "msgspec") or name.startswith("hapticproxy.protocol"):
                    continue
                if top in PROTOCOL_EXTRA and PROTOCOL_EXTRA[top] in rel:
                    continue
                bad.append(f"protocol/{rel}: {name}")
            elif folder == "server" and name.startswith("hapticproxy.clients"):
                bad.append(f"server/{rel}: {name}")
            elif folder == "clients" and name.startswith("hapticproxy.server"):
                bad.append(f"clients/{rel}: {name}")
            elif name.startswith("hapticproxy.") and not name.startswith(("hapticproxy.protocol", PACKAGES[folder])):
                bad.append(f"{folder}/{rel}: {name}")
    return bad


@pytest.mark.parametrize("folder", sorted(PACKAGES))
def test_dependency_direction(folder):
    files = {str(p.relative_to(ROOT / folder)): p.read_text() for p in (ROOT / folder).rglob("*.py")}
    assert files, f"{folder}/ has no modules"
    assert violations(folder, files) == []


def test_the_checker_catches_violations():
    assert violations("protocol", {"codec.py": "import numba\n"}) == ["protocol/codec.py: numba"]
    assert violations("protocol", {"codec.py": "from ..server import model\n"}) == \
        ["protocol/codec.py: hapticproxy.server"]
    assert violations("protocol", {"transport/udp.py": "import zenoh\n"}) == ["protocol/transport/udp.py: zenoh"]
    assert violations("protocol", {"transport/zenoh.py": "import zenoh\n"}) == []
    assert violations("server", {"loop.py": "from hapticproxy.clients import pymunk_client\n"}) != []
    assert violations("clients", {"a/b.py": "from ...server.model import LocalModel\n"}) != []
    assert violations("server", {"loop.py": "from hapticproxy.cli import main\n"}) != []
    assert violations("server", {"loop.py": "from hapticproxy.protocol import messages\nimport numba\n"}) == []


#: every folder of the ``hapticproxy`` namespace (``pyproject.toml``'s package-dir roots)
NAMESPACE = {"protocol": "hapticproxy.protocol", "server": "hapticproxy.server", "clients": "hapticproxy.clients",
             "cli": "hapticproxy.cli", "benchmarks": "hapticproxy.benchmarks",
             "experiments": "hapticproxy.experiments", "testing": "hapticproxy.testing"}
#: folders under a namespace folder that are not part of the package (standalone examples)
NOT_PACKAGE = ("clients/examples/",)


def _package_modules() -> dict[str, tuple[Path, bool]]:
    """module name -> (file, is_package) for every module of the namespace."""
    out = {}
    for folder, pkg in NAMESPACE.items():
        for p in (ROOT / folder).rglob("*.py"):
            rel = str(p.relative_to(ROOT))
            if "__pycache__" in rel or rel.startswith(NOT_PACKAGE):
                continue
            parts = str(p.relative_to(ROOT / folder))[:-3].split("/")
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            out[".".join([pkg] + parts)] = (p, is_package)
    return out


def absolute_self_imports(source: str) -> list[str]:
    """``from hapticproxy... import`` / ``import hapticproxy...`` statements (at any depth)."""
    bad = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").startswith("hapticproxy"):
            bad.append(f"line {node.lineno}: from {node.module}")
        elif isinstance(node, ast.Import):
            bad.extend(f"line {node.lineno}: import {a.name}" for a in node.names if a.name.startswith("hapticproxy"))
    return bad


def test_imports_inside_the_package_are_relative():
    """A reader (pyright, pylint, a person) follows ``from ..protocol import vocab`` from the file
    itself; ``hapticproxy.protocol`` exists only through the install's mapping of folders."""
    bad = {}
    for name, (path, _) in _package_modules().items():
        found = absolute_self_imports(path.read_text())
        if found:
            bad[name] = found
    assert bad == {}


def mutual_imports(modules: dict[str, tuple[str, bool]]) -> list[tuple[str, str]]:
    """Pairs of modules that import each other (at any depth: a function's own import counts).
    ``modules``: name -> (source, is_package)."""
    graph = {}
    for name, (source, is_package) in modules.items():
        deps = set()
        for dep in imports_of(source, name, is_package):
            # "from . import x" names x (a module) or an attribute of the package: keep the longest
            # prefix that is a module
            while dep and dep not in modules:
                dep = dep.rpartition(".")[0]
            if dep and dep != name:
                deps.add(dep)
        graph[name] = deps
    return sorted((a, b) for a in graph for b in graph[a] if a < b and a in graph.get(b, ()))


def test_no_two_modules_import_each_other():
    mods = {name: (path.read_text(), pkg) for name, (path, pkg) in _package_modules().items()}
    assert mutual_imports(mods) == []


def test_the_cycle_checker_catches_a_pair():
    mods = {"hapticproxy.server.a": ("from . import b\n", False),
            "hapticproxy.server.b": ("def f():\n    from .a import x\n", False),
            "hapticproxy.server.c": ("from .a import y\n", False)}
    assert mutual_imports(mods) == [("hapticproxy.server.a", "hapticproxy.server.b")]
    assert absolute_self_imports("def f():\n    from hapticproxy.server import loop\n") == \
        ["line 2: from hapticproxy.server"]


def test_the_architecture_page_shows_the_fault_policy_as_declared():
    from hapticproxy.server.lifecycle import policy_table

    assert policy_table() in (ROOT / "docs" / "architecture.md").read_text()


#: the modules that declare array layouts (named columns of the arrays the kernels share)
LAYOUT_MODULES = ("server/model/layout.py", "server/devices/layout.py", "server/control.py", "server/safety.py",
                  "server/tick.py", "server/servo.py", "server/devices/hd_native.py", "server/shm.py",
                  "server/devices/frozen.py", "server/devices/mapping.py")


#: not columns but vocabulary several layouts share on purpose: return codes (the controller's
#: extend the safety filter's) and size limits
SHARED_PREFIXES = ("RC_", "MAX_")


def layout_prefixes(sources: dict[str, str]) -> dict[str, set[str]]:
    """prefix (the name up to its first underscore) -> the layout modules that declare an
    upper-case integer constant with it (``CS_GAIN`` -> ``CS``)."""
    out: dict[str, set[str]] = {}
    for path, src in sources.items():
        for node in ast.parse(src).body:
            if not (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)):
                continue
            name = node.targets[0].id
            if not name.isupper() or "_" not in name or name.startswith("_") or name.startswith(SHARED_PREFIXES):
                continue
            v = node.value
            if isinstance(v, ast.Constant) and isinstance(v.value, int) or isinstance(v, (ast.BinOp, ast.Attribute)):
                out.setdefault(name.split("_", 1)[0], set()).add(path)
    return out


def test_no_two_layouts_share_a_prefix():
    """A column constant names its array by its prefix: ``P_AXIS`` meant 21 in the model's layout
    and 15 in the simulated device's, ``CS_*`` the controller's state and the model's contact
    states. Each prefix belongs to one layout module."""
    sources = {m: (ROOT / m).read_text() for m in LAYOUT_MODULES}
    shared = {p: sorted(ms) for p, ms in layout_prefixes(sources).items() if len(ms) > 1}
    assert shared == {}


def test_the_prefix_checker_sees_a_collision():
    got = layout_prefixes({"a.py": "P_AXIS = 21\nCS_GAIN = 0\n", "b.py": "P_AXIS = 15\nTK_X = CS + 1\n"})
    assert got["P"] == {"a.py", "b.py"} and got["CS"] == {"a.py"} and got["TK"] == {"b.py"}
