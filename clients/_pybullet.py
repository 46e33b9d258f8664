"""pybullet, imported once without the build-date line its C extension prints on stdout at
import (``pybullet build time: ...``): a command's stdout is its output (``--json``, a listing)."""
from __future__ import annotations

import os
import sys

try:
    sys.stdout.flush()
    _saved = os.dup(1)
except (OSError, ValueError):  # no real stdout (a captured one): nothing to silence
    _saved = None
if _saved is not None:
    _null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(_null, 1)
try:
    import pybullet as p  # noqa: E402
finally:
    if _saved is not None:
        os.dup2(_saved, 1)
        os.close(_saved)
        os.close(_null)

__all__ = ["p"]
