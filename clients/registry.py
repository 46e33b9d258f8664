"""The engine registry: every environment engine is found by name in the ``hapticproxy.engines``
entry-point group.

The built-ins (``stub``, ``pymunk``, ``pybullet``, ``pybullet-linkage``, ``peg1d``) are declared
there by hapticproxy's own ``pyproject.toml``; any installed package adds its own engines the same
way, from its own ``pyproject.toml``, without touching this one::

    [project.entry-points."hapticproxy.engines"]
    mylab = "mylab.engine:MyLabEngine"     # a subclass of hapticproxy.clients.engine.Engine

after which ``hapticproxy client --list`` shows it and ``hapticproxy client mylab`` runs it (and
:mod:`.contract` tests it). The pattern is python-can's (``can/interfaces/__init__.py``: built-in
backends merged with the ``can.interface`` entry points). A name is taken by hapticproxy's own
entry first: another package's entry of the same name is listed as ignored, never silently put
in its place. Engines are imported only when chosen (:func:`load_engine_class`), so an engine
whose library is missing does not affect the others.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from importlib.metadata import entry_points

__all__ = ["GROUP", "EngineEntry", "engines", "load_engine_class", "availability"]

#: the entry-point group engines register in
GROUP = "hapticproxy.engines"
_OWN_DISTRIBUTION = "hapticproxy"


@dataclass(frozen=True)
class EngineEntry:
    """One registered engine: ``target`` is the entry point's ``module:attr``."""

    name: str
    target: str
    #: the distribution that declared it ("name version"; "" if unknown)
    package: str
    builtin: bool
    #: entries of the same name from other packages, not used ("package: target")
    ignored: tuple[str, ...] = ()


def _entry_points() -> list:
    return list(entry_points(group=GROUP))


def _package(ep) -> tuple[str, bool]:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return "", False
    name = dist.metadata["Name"] or ""
    return f"{name} {dist.version}", name.lower().replace("_", "-") == _OWN_DISTRIBUTION


def engines() -> dict[str, EngineEntry]:
    """Every registered engine by name: hapticproxy's own first, then the other packages', each
    part sorted by name."""
    own: dict[str, EngineEntry] = {}
    others: dict[str, list] = {}
    for ep in sorted(_entry_points(), key=lambda e: e.name):
        package, builtin = _package(ep)
        if builtin:
            if ep.name not in own:
                own[ep.name] = EngineEntry(ep.name, ep.value, package, True)
        else:
            others.setdefault(ep.name, []).append((package, ep.value))
    out = dict(own)
    for name in sorted(others):
        entries = others[name]
        if name in out:
            e = out[name]
            out[name] = EngineEntry(e.name, e.target, e.package, e.builtin,
                                    tuple(f"{pkg}: {value}" for pkg, value in entries))
            continue
        (package, value), rest = entries[0], entries[1:]
        out[name] = EngineEntry(name, value, package, False, tuple(f"{pkg}: {v}" for pkg, v in rest))
    return out


def load_engine_class(name: str, registry: dict[str, EngineEntry] | None = None):
    """The engine class registered as ``name``; ``ValueError`` (one line) if it is unknown, its
    module or a library it needs is missing, or it is not an :class:`~.engine.Engine`."""
    from .engine import Engine

    registry = engines() if registry is None else registry
    if name not in registry:
        raise ValueError(f"unknown engine {name!r}; choose one of: {', '.join(registry) or '(none registered)'}")
    module_name, _, attr = registry[name].target.partition(":")
    try:
        obj = importlib.import_module(module_name.strip())
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if missing and module_name.strip().startswith(missing):
            raise ValueError(f"engine {name!r} is not available in this build ({module_name.strip()} is missing)") from None
        raise ValueError(f"engine {name!r} needs the {missing!r} package, which is not installed") from None
    for part in attr.strip().split(".") if attr.strip() else ():
        obj = getattr(obj, part, None)
        if obj is None:
            raise ValueError(f"engine {name!r}: {module_name.strip()} has no {attr.strip()}")
    if not (isinstance(obj, type) and issubclass(obj, Engine)):
        raise ValueError(f"engine {name!r}: {registry[name].target} is not an Engine subclass")
    return obj


def availability(name: str, registry: dict[str, EngineEntry] | None = None) -> str:
    """"" when the engine loads, else the one-line reason it does not."""
    try:
        load_engine_class(name, registry)
    except ValueError as exc:
        return str(exc)
    return ""
