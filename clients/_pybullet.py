"""pybullet, imported once without the build-date line its C extension prints at import
(``pybullet build time: ...``, on stderr in the wheels we pin, on stdout in some builds): a
command's stdout is its output (``--json``, a listing), its stderr is what a person should read.
An import error still raises (after both are restored)."""
from __future__ import annotations

import os
import sys

_saved: list[tuple[int, int]] = []
for _fd, _stream in ((1, sys.stdout), (2, sys.stderr)):
    try:
        _stream.flush()
        _saved.append((_fd, os.dup(_fd)))
    except (AttributeError, OSError, ValueError):  # no real stream (a captured one): nothing to silence
        pass
_null = os.open(os.devnull, os.O_WRONLY)
for _fd, _ in _saved:
    os.dup2(_null, _fd)
try:
    import pybullet as p  # noqa: E402
finally:
    for _fd, _copy in _saved:
        os.dup2(_copy, _fd)
        os.close(_copy)
    os.close(_null)

__all__ = ["p"]
