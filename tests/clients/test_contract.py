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


class TestAnEngineBuiltByTheLab(EngineContract):
    """The other way a lab runs the suite: it builds its engine itself (no registry entry)."""

    scenes = ("wall",)
    engine = "stub-seed-5"

    def make_engine(self):
        from hapticproxy.clients.stub_engine import StubEngine

        return StubEngine(seed=5)


# ------------------------------------------------------------------ the suite catches broken engines
def _broken(kind):
    import random

    from hapticproxy.clients.stub_engine import StubEngine

    class Broken(StubEngine):
        def load_scene(self, name):
            if kind == "accepts-any-scene" and name not in self.scenes():
                name = "wall"
            return super().load_scene(name)

        def drive_tool(self, proxy_pose, proxy_twist, wrench):
            if kind != "ignores-the-proxy":
                super().drive_tool(proxy_pose, proxy_twist, wrench)

        def contacts(self, buf, max_contacts):
            n = super().contacts(buf, max_contacts)
            if n and kind == "duplicate-keys" and n < max_contacts:
                buf.keys[n] = buf.keys[0]
                buf.position_m[n], buf.normal[n] = buf.position_m[0], buf.normal[0]
                buf.separation_m[n], buf.v_constr_m_per_s[n] = buf.separation_m[0], buf.v_constr_m_per_s[0]
                n = buf.n = n + 1
            if n and kind == "long-normals":
                buf.normal[:n] *= 1.01
            return n

        @property
        def time_s(self):
            return self._t * (1.5 if kind == "slow-clock" else 1.0)

        def tool_pose(self, out):
            super().tool_pose(out)
            if kind == "not-deterministic":
                out[0] += 1e-9 * random.random()
            return out

    Broken.__name__ = f"Broken_{kind.replace('-', '_')}"
    return Broken


@pytest.mark.parametrize("kind, check", [
    ("accepts-any-scene", "test_scenes_describe_a_tool_the_server_accepts"),
    ("slow-clock", "test_steps_at_its_declared_rate_in_simulated_time"),
    ("duplicate-keys", "test_contacts_fit_the_grant_with_unit_normals_and_unique_keys"),
    ("long-normals", "test_contacts_fit_the_grant_with_unit_normals_and_unique_keys"),
    ("ignores-the-proxy", "test_the_tool_follows_a_driven_proxy"),
    ("not-deterministic", "test_is_deterministic_when_it_says_so"),
])
def test_the_suite_fails_an_engine_that_breaks_the_contract(kind, check):
    from hapticproxy.clients.contract import _Subject

    cls = _broken(kind)
    suite = EngineContract()
    subject = _Subject(f"broken-{kind}", cls, {}, ("wall",), cls)
    with pytest.raises(AssertionError):
        getattr(suite, check)(subject)
    # and the same check passes for the engine it was broken from
    good = _Subject(f"unbroken-{kind}", _broken("none"), {}, ("wall",), _broken("none"))
    getattr(suite, check)(good)
