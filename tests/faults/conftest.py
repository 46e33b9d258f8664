"""The fault tests reuse the server-loop harness of tests/server (``from server_harness import ...``)
and its ``rig_factory`` fixture; with ``--import-mode=importlib`` test folders are not on
``sys.path`` by themselves."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))

from server_harness import rig_factory  # noqa: E402,F401
