"""One plug-in registry for engines, device drivers and transports: built-ins merged with entry points.

The pattern is python-can's (``can/interfaces/__init__.py``): a table of the built-in backends
(name -> ``"module:attr"``) in the code, merged with what any installed package declares in an
entry-point group from its own ``pyproject.toml``::

    [project.entry-points."hapticproxy.engines"]      # or .devices, .transports
    mylab = "mylab.engine:MyLabEngine"

Unlike python-can, a built-in name is never replaced: another package's entry of the same name
is listed as ignored (``hapticproxy client --list``, ``hapticproxy plugins``), so an installed
package cannot silently swap the driver of a haptic device. Nothing is imported until it is
chosen (:meth:`Registry.load`), so a plug-in whose library is missing affects no other.

The three registries (each declared once, next to what it registers):

- engines: ``hapticproxy.clients.registry.ENGINES`` (group ``hapticproxy.engines``)
- device drivers: ``hapticproxy.server.devices.base.DEVICES`` (group ``hapticproxy.devices``)
- transports, by URL scheme: ``hapticproxy.protocol.transport.TRANSPORTS`` (group
  ``hapticproxy.transports``)
"""
from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, entry_points, version
from typing import Any

__all__ = ["Entry", "Registry"]

_OWN_DISTRIBUTION = "hapticproxy"


def _own_package() -> str:
    try:
        return f"{_OWN_DISTRIBUTION} {version(_OWN_DISTRIBUTION)}"
    except PackageNotFoundError:  # a source tree on sys.path, not installed
        return _OWN_DISTRIBUTION


@dataclass(frozen=True)
class Entry:
    """One registered plug-in: ``target`` is its ``module:attr``."""

    name: str
    target: str
    #: the distribution that declared it ("name version"; "" if unknown)
    package: str
    builtin: bool
    #: entries of the same name from other packages, not used ("package: target")
    ignored: tuple[str, ...] = ()


def _package(ep) -> str:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return ""
    return f"{dist.metadata['Name'] or ''} {dist.version}"


def _is_own(ep) -> bool:
    dist = getattr(ep, "dist", None)
    name = (dist.metadata["Name"] or "") if dist is not None else ""
    return name.lower().replace("_", "-") == _OWN_DISTRIBUTION


class Registry:
    """Plug-ins of one ``kind`` ("engine", "device", "transport"): ``builtins`` (name ->
    ``"module:attr"``) merged with the entry-point ``group``.

    ``check(name, obj)`` (optional) is called on what :meth:`load` imported and returns "" when
    it is the right kind of object, else why not (e.g. "is not an Engine subclass").
    ``field`` names the setting that chooses a plug-in in error messages (``device.driver``)."""

    def __init__(self, kind: str, group: str, builtins: Mapping[str, str], *,
                 check: Callable[[str, Any], str] | None = None, field: str = "") -> None:
        self.kind = kind
        self.group = group
        self.builtins = dict(builtins)
        self.check = check
        self.field = field

    def _prefix(self) -> str:
        return f"{self.field}: " if self.field else ""

    def entries(self) -> dict[str, Entry]:
        """Every registered plug-in by name: the built-ins first, then the other packages', each
        part sorted by name. Read afresh on each call (an installed package may come and go)."""
        own = _own_package()
        out = {name: Entry(name, target, own, True) for name, target in sorted(self.builtins.items())}
        others: dict[str, list[tuple[str, str]]] = {}
        for ep in sorted(entry_points(group=self.group), key=lambda e: e.name):
            if _is_own(ep) and ep.name in out:
                continue  # hapticproxy's own metadata naming a built-in: the same declaration
            others.setdefault(ep.name, []).append((_package(ep), ep.value))
        for name in sorted(others):
            found = others[name]
            if name in out:
                e = out[name]
                out[name] = Entry(e.name, e.target, e.package, e.builtin, tuple(f"{p}: {v}" for p, v in found))
                continue
            (package, target), rest = found[0], found[1:]
            out[name] = Entry(name, target, package, False, tuple(f"{p}: {v}" for p, v in rest))
        return out

    def names(self) -> list[str]:
        return list(self.entries())

    def known(self, name: str) -> bool:
        """Whether ``name`` is registered (a built-in is known without reading the entry points)."""
        return name in self.builtins or name in self.entries()

    def load(self, name: str, entries: Mapping[str, Entry] | None = None) -> Any:
        """The object registered as ``name``, imported now. ``ValueError`` (one line) when the
        name is unknown, its module or a library it needs is missing, or ``check`` refuses it."""
        if entries is None and name in self.builtins:
            target = self.builtins[name]  # a built-in is never replaced: no need to read the entry points
        else:
            entries = self.entries() if entries is None else entries
            if name not in entries:
                raise ValueError(f"{self._prefix()}unknown {self.kind} {name!r}; choose one of: "
                                 f"{', '.join(entries) or '(none registered)'}")
            target = entries[name].target
        module_name, _, attr = (s.strip() for s in target.partition(":"))
        try:
            obj = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            missing = exc.name or ""
            if missing and module_name.startswith(missing):
                raise ValueError(f"{self._prefix()}{self.kind} {name!r} is not available in this build "
                                 f"({module_name} is missing)") from None
            raise ValueError(f"{self._prefix()}{self.kind} {name!r} needs the {missing!r} package, "
                             "which is not installed") from None
        for part in attr.split(".") if attr else ():
            obj = getattr(obj, part, None)
            if obj is None:
                raise ValueError(f"{self._prefix()}{self.kind} {name!r}: {module_name} has no {attr}")
        why = self.check(name, obj) if self.check is not None else ""
        if why:
            raise ValueError(f"{self._prefix()}{self.kind} {name!r}: {target} {why}")
        return obj

    def availability(self, name: str, entries: Mapping[str, Entry] | None = None) -> str:
        """"" when ``name`` loads here, else the one-line reason it does not."""
        try:
            self.load(name, entries)
        except ValueError as exc:
            return str(exc)
        return ""

    def rows(self, describe: Callable[[str, Any], dict] | None = None) -> list[dict]:
        """One dict per plug-in (what ``--list`` prints): name, target, package, builtin,
        available, reason, ignored, plus ``describe(name, obj)`` of the ones that load."""
        entries = self.entries()
        out = []
        for name, e in entries.items():
            why = self.availability(name, entries)
            row = {"kind": self.kind, "name": name, "target": e.target, "package": e.package, "builtin": e.builtin,
                   "available": not why, "reason": why, "ignored": list(e.ignored)}
            if not why and describe is not None:
                row.update(describe(name, self.load(name, entries)))
            out.append(row)
        return out


def format_rows(rows: list[dict], detail: Callable[[dict], str] = lambda r: "") -> list[str]:
    """The text lines of ``--list``: ``name  target  (package)  detail | not available: why``,
    then one line per ignored entry of the same name."""
    width = max((len(r["name"]) for r in rows), default=4)
    lines = []
    for r in rows:
        status = detail(r) if r["available"] else f"not available: {r['reason']}"
        lines.append(f"{r['name']:<{width}}  {r['target']}  ({r['package'] or 'unknown package'})"
                     + (f"  {status}" if status else ""))
        for other in r["ignored"]:
            lines.append(f"{'':<{width}}  ignored, the name is taken: {other}")
    return lines
