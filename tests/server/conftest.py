"""Makes the server-test harness importable (``from server_harness import ...``) and its fixtures
available; with ``--import-mode=importlib`` test folders are not on ``sys.path`` by themselves."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from server_harness import rig_factory  # noqa: E402,F401
