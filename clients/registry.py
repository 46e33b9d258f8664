"""The engine registry: environment engines by name, the built-ins merged with the
``hapticproxy.engines`` entry-point group (:mod:`hapticproxy.protocol.registry`, the one
registry pattern of engines, device drivers and transports).

The built-ins are :data:`ENGINES`; any installed package adds its own engines from its own
``pyproject.toml``, without touching this one::

    [project.entry-points."hapticproxy.engines"]
    mylab = "mylab.engine:MyLabEngine"     # a subclass of hapticproxy.clients.engine.Engine

after which ``hapticproxy client --list`` shows it and ``hapticproxy client mylab`` runs it (and
:mod:`.contract` tests it). A built-in name is never taken over: another package's entry of the
same name is listed as ignored. Engines are imported only when chosen
(:func:`load_engine_class`), so an engine whose library is missing does not affect the others.
"""
from __future__ import annotations

from ..protocol.registry import Entry, Registry

__all__ = ["ENGINES", "GROUP", "EngineEntry", "REGISTRY", "engines", "load_engine_class", "availability"]

#: the entry-point group engines register in
GROUP = "hapticproxy.engines"
#: the built-in engines (name -> module:class)
ENGINES = {
    "stub": "hapticproxy.clients.stub_engine:StubEngine",
    "pymunk": "hapticproxy.clients.pymunk_engine:PymunkEngine",
    "pybullet": "hapticproxy.clients.pybullet_engine:PybulletEngine",
    "pybullet-linkage": "hapticproxy.clients.pybullet_linkage:PybulletLinkageEngine",
    "peg1d": "hapticproxy.clients.peg_engine:PegEngine",
}
#: one registered engine (``target`` is its ``module:attr``)
EngineEntry = Entry


def _is_engine(name: str, obj) -> str:
    from .engine import Engine

    return "" if isinstance(obj, type) and issubclass(obj, Engine) else "is not an Engine subclass"


REGISTRY = Registry("engine", GROUP, ENGINES, check=_is_engine)


def engines() -> dict[str, EngineEntry]:
    """Every registered engine by name: the built-ins first, then the other packages', each part
    sorted by name."""
    return REGISTRY.entries()


def load_engine_class(name: str, registry: dict[str, EngineEntry] | None = None):
    """The engine class registered as ``name``; ``ValueError`` (one line) if it is unknown, its
    module or a library it needs is missing, or it is not an :class:`~.engine.Engine`."""
    return REGISTRY.load(name, registry)


def availability(name: str, registry: dict[str, EngineEntry] | None = None) -> str:
    """"" when the engine loads, else the one-line reason it does not."""
    return REGISTRY.availability(name, registry)
