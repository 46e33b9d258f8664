"""``hapticproxy plugins [--kind engine|device|transport] [--json]``: every registered plug-in.

The three registries (:mod:`hapticproxy.protocol.registry`): environment engines
(``hapticproxy.engines``), device drivers (``hapticproxy.devices``) and transports by URL
scheme (``hapticproxy.transports``), each the built-ins merged with what installed packages
declare. One line per plug-in: name, ``module:attr``, the package that declared it, and whether
it loads here (the reason when not); an installed package's entry that tries to take a built-in
name is shown as ignored.
"""
from __future__ import annotations

import argparse
import sys

from ..protocol.jsonout import print_json
from ..protocol.registry import Registry, format_rows

KINDS = ("engine", "device", "transport")


def registries() -> dict[str, Registry]:
    from ..clients.registry import REGISTRY as ENGINES
    from ..protocol.transport import TRANSPORT_REGISTRY
    from ..server.devices.base import DEVICE_REGISTRY

    return {"engine": ENGINES, "device": DEVICE_REGISTRY, "transport": TRANSPORT_REGISTRY}


def _describe(kind: str):
    if kind == "engine":
        return lambda name, cls: {"scenes": list(cls.scenes())}
    if kind == "transport":
        return lambda name, cls: {"url_form": f"{name}://{cls.url_form}"}
    return _device_about


def _device_about(name: str, factory) -> dict:
    """A device driver's ``about`` (its factory's attribute): who owns the clock, the vendor
    package it needs and whether that is installed, the models it knows."""
    import importlib.util

    about = dict(getattr(factory, "about", None) or {})
    pkg = about.get("module")
    if pkg:
        about["package_installed"] = importlib.util.find_spec(pkg) is not None
    return {"device": about}


def _detail(r: dict) -> str:
    if "scenes" in r:
        return f"scenes: {', '.join(r['scenes'])}"
    if "url_form" in r:
        return f"url: {r['url_form']}"
    if r.get("device"):
        a = r["device"]
        out = [f"clock: {a['clock']}"] if a.get("clock") else []
        if a.get("package"):
            out.append(f"needs {a['package']} ({'installed' if a.get('package_installed') else 'not installed: pip install hapticproxy[devices]'})")
        if a.get("models"):
            out.append("models: " + ", ".join(a["models"]))
        return "; ".join(out)
    return ""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="hapticproxy plugins", description=__doc__.splitlines()[0].split(": ", 1)[1])
    p.add_argument("--kind", choices=KINDS, action="append", help="only this kind (repeatable; default: all)")
    p.add_argument("--json", action="store_true", help="print a JSON list of rows")
    args = p.parse_args(argv)
    regs = registries()
    kinds = args.kind or list(KINDS)
    rows = {kind: regs[kind].rows(_describe(kind)) for kind in kinds}
    if args.json:
        print_json([r for kind in kinds for r in rows[kind]], sort_keys=True)
        return 0
    lines = []
    for kind in kinds:
        lines.append(f"{kind}s ({regs[kind].group}):")
        lines.extend(f"  {ln}" for ln in format_rows(rows[kind], _detail))
    sys.stdout.write("\n".join(lines) + "\n")
    return 0
