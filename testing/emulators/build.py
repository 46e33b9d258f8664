"""Compile the fake vendor libraries (``libdrd.so``, ``libHD.so``) with the machine's C compiler.

Each is built from its C source in this folder plus headers generated from the Python
declarations (the block layout, :mod:`.block`; the models' names and figures,
``server/devices/models.py``), so the C and the Python never disagree. ``libdrd.so`` also gets
a stub for every other symbol the *installed* ``forcedimension-core`` binds at import (found by
reading the package's source: each ``<lib>.<symbol>.restype = ...``), failing with
``DHD_ERROR_NOT_IMPLEMENTED``: the unmodified package imports, whatever its version binds.

:func:`build_libdrd` lays the library out as the Force Dimension SDK does
(``<root>/lib/release/lin-<machine>-gcc/libdrd.so.<version>``), so ``FDSDK=<root>`` is what a
user sets for the real one; :func:`build_libhd` writes ``<dir>/libHD.so`` (SONAME ``libHD.so``).
Builds are cached per process by output folder.
"""
from __future__ import annotations

import ast
import importlib.util
import os
import platform
import shutil
import subprocess
from pathlib import Path

from ...server.devices import models
from .block import c_header

HERE = Path(__file__).resolve().parent
#: the symbols the hand-written C defines (the rest of what the package binds are stubs)
_CTYPE = {"c_int": "int", "c_bool": "_Bool", "c_double": "double", "c_char_p": "const char *", "None": "void",
          "c_byte": "signed char", "c_uint": "unsigned int", "c_ushort": "unsigned short", "c_ubyte": "unsigned char"}


class BuildError(RuntimeError):
    pass


def compiler() -> str:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        raise BuildError("no C compiler (cc) on PATH: the emulators of the vendor libraries need one")
    return cc


def _models_header() -> str:
    out = ["/* generated from hapticproxy.server.devices.models: do not edit */",
           "struct emu_fd_model { int type; const char *name; double max_force_n, max_torque_n_m, max_gripper_force_n;",
           "  int sensed_rotation, actuated_rotation, sensed_gripper, actuated_gripper; };",
           "static const struct emu_fd_model EMU_FD_MODELS[] = {"]
    for t, m in models.FORCEDIMENSION.items():
        out.append(f'  {{{t}, "{m.name}", {m.max_force_n!r}, {m.max_torque_n_m!r}, {m.max_gripper_force_n!r}, '
                   f'{int("rotation" in m.sensed)}, {int("rotation" in m.actuated)}, {int("gripper" in m.sensed)}, '
                   f'{int("gripper" in m.actuated)}}},')
    out += ["};",
            "static const struct emu_fd_model *emu_fd_model(int type) {",
            "  for (unsigned i = 0; i < sizeof EMU_FD_MODELS / sizeof EMU_FD_MODELS[0]; i++)",
            "    if (EMU_FD_MODELS[i].type == type) return &EMU_FD_MODELS[i];",
            "  return 0;", "}",
            "struct emu_hd_model { const char *name, *vendor; double max_force_n, stiffness_n_per_m, damping_n_s_per_m,",
            "  workspace_radius_m; int buttons; };",
            "static const struct emu_hd_model EMU_HD_MODELS[] = {"]
    for m in models.TOUCH.values():
        out.append(f'  {{"{m.name}", "{m.vendor}", {m.max_force_n!r}, {m.max_stiffness_n_per_m or 0.0!r}, '
                   f'{m.max_damping_n_s_per_m or 0.0!r}, {m.workspace_radius_m!r}, {m.buttons}}},')
    out += ["};", f"#define EMU_HD_NMODELS {len(models.TOUCH)}"]
    return "\n".join(out) + "\n"


def package_symbols(package: str) -> dict[str, tuple[str, list[str]]]:
    """``{symbol: (restype, argtypes)}`` as the installed ``package`` binds them (its source read,
    not imported: importing it needs the library this builds)."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise BuildError(f"{package} is not installed (pip install 'hapticproxy[devices]')")
    res: dict[str, str] = {}
    args: dict[str, list[str]] = {}
    for root in spec.submodule_search_locations:
        for f in Path(root).rglob("*.py"):
            for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Assign) and len(node.targets) == 1:
                    t = node.targets[0]
                    if isinstance(t, ast.Attribute) and t.attr in ("argtypes", "restype") \
                            and isinstance(t.value, ast.Attribute):
                        if t.attr == "restype":
                            res[t.value.attr] = ast.unparse(node.value)
                        elif isinstance(node.value, ast.List):
                            args[t.value.attr] = [ast.unparse(e) for e in node.value.elts]
    return {name: (res.get(name, "c_int"), args.get(name, [])) for name in set(res) | set(args)}


def _defined(c_source: str) -> set[str]:
    import re

    return set(re.findall(r"^[A-Za-z_][\w \*]*?\b((?:dhd|drd|hd|hdu)\w+)\s*\(", c_source, re.M))


def _stubs(symbols: dict[str, tuple[str, list[str]]], defined: set[str], error_fn: str) -> str:
    out = ["/* generated: every symbol the package binds that the emulator does not implement */",
           f"extern void {error_fn}(int);"]
    for name in sorted(symbols):
        if name in defined:
            continue
        ret = _CTYPE.get(symbols[name][0], "int")
        body = {"void": "", "double": "return -1.0;", "const char *": "return 0;", "_Bool": "return 0;"}.get(
            ret, "return -1;")
        out.append(f"{ret} {name}(void) {{ {error_fn}(10); {body} }}")
    return "\n".join(out) + "\n"


def _cc(sources: list[Path], out: Path, soname: str, incdir: Path) -> None:
    cmd = [compiler(), "-shared", "-fPIC", "-O2", "-std=gnu11", f"-Wl,-soname,{soname}", f"-I{incdir}",
           "-o", str(out), *map(str, sources), "-lm", "-lpthread"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        raise BuildError(f"compiling {out.name} failed:\n{r.stderr}")


_BUILT: dict[str, Path] = {}


def build_libdrd(root: str | os.PathLike) -> Path:
    """Build the fake Force Dimension SDK under ``root`` (what ``FDSDK`` is set to); returns the
    library's path."""
    root = Path(root)
    key = f"drd:{root}"
    if key in _BUILT:
        return _BUILT[key]
    src = HERE / "libdrd_emu.c"
    gen = root / "src"
    gen.mkdir(parents=True, exist_ok=True)
    (gen / "emu_block.h").write_text(c_header())
    (gen / "emu_models.h").write_text(_models_header())
    text = src.read_text()
    syms = package_symbols("forcedimension_core")
    stubs = _stubs(syms, _defined(text), "emu_drd_set_error")
    (gen / "emu_stubs.c").write_text(stubs + "\n")
    (gen / "emu_err.c").write_text("")
    lib_dir = root / "lib" / "release" / f"lin-{platform.machine()}-gcc"
    lib_dir.mkdir(parents=True, exist_ok=True)
    out = lib_dir / "libdrd.so.3.17.6"
    _cc([src, gen / "emu_stubs.c"], out, "libdrd.so.3", gen)
    _BUILT[key] = out
    return out


def build_libhd(folder: str | os.PathLike) -> Path:
    """Build the fake OpenHaptics HD library as ``<folder>/libHD.so``."""
    folder = Path(folder)
    key = f"hd:{folder}"
    if key in _BUILT:
        return _BUILT[key]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "emu_block.h").write_text(c_header())
    (folder / "emu_models.h").write_text(_models_header())
    out = folder / "libHD.so"
    _cc([HERE / "libhd_emu.c"], out, "libHD.so", folder)
    _BUILT[key] = out
    return out
