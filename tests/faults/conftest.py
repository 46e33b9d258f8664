"""The fault tests reuse the server-loop harness of tests/server (``from server_harness import ...``)
and its ``rig_factory`` fixture; with ``--import-mode=importlib`` test folders are not on
``sys.path`` by themselves."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))

from server_harness import rig_factory  # noqa: E402,F401

import pytest  # noqa: E402


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Each phase's report on the test item (``item.rep_setup``, ``rep_call``): a fixture can tell
    after ``yield`` whether its test failed (``test_attacks.live`` replaces a server then)."""
    outcome = yield
    rep = outcome.get_result()
    setattr(item, f"rep_{rep.when}", rep)
