"""The engine contract (``hapticproxy.clients.contract``) run against every registered engine,
as a lab runs it against its own: parametrised over the registry (built-ins and any installed
package's engines)."""
from __future__ import annotations

import pytest

from hapticproxy.clients.contract import EngineContract
from hapticproxy.clients.registry import engines


def _server_accepts(hello) -> str:
    """The real server's check of the Hello's tool (a linkage on a planar or a spatial device)."""
    from hapticproxy.server.loop import tool_from_hello

    errors = []
    for planar in ((None,) if int(hello.tool_kind) != 4 else (True, False)):
        try:
            tool_from_hello(hello, planar=planar)
            return ""
        except ValueError as exc:
            errors.append(str(exc))
    return "; ".join(errors)


class TestEveryRegisteredEngine(EngineContract):
    hello_check = staticmethod(_server_accepts)

    @pytest.fixture(params=sorted(engines()))
    def engine_name(self, request):
        return request.param


class TestALabsEnginePackage(EngineContract):
    """The suite as a lab runs it from its own package: its engine registered by its own
    distribution's entry point (here a stub subclass, one scene)."""

    engine = "lab"
    scenes = ("wall",)

    @pytest.fixture
    def engine_name(self, lab_package):
        return self.engine
