"""Strict JSON for everything a command prints with ``--json`` (and the status server's replies).

Strict means what any JSON parser accepts and what a reader expects: integers as integers (a
numpy ``int64`` or a counter is never ``3.0``), no ``NaN`` / ``Infinity`` (a value not known is
``null``), numpy scalars and arrays as plain numbers and lists. One converter, used by the server
and by the clients (both may import ``protocol``), so every ``--json`` follows the same rules.
"""
from __future__ import annotations

import enum
import json
import math
import os
import sys
from collections.abc import Mapping
from typing import IO, Any

__all__ = ["jsonable", "dumps", "print_json"]


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values: every non-finite float as ``None``, numpy scalars and arrays
    as Python numbers and lists, tuples and sets as lists, an ``IntEnum`` as its number, any
    other enum as its name, any other object as ``str(obj)``. ``json.dumps(jsonable(x), allow_nan=False)`` never fails."""
    if obj is None or isinstance(obj, str):
        return obj
    # numpy is not imported here: when no one imported it, no value can be one of its types
    # (and ``hapticproxy status --json`` starts without it)
    np = sys.modules.get("numpy")
    if isinstance(obj, bool) or (np is not None and isinstance(obj, np.bool_)):
        return bool(obj)
    if isinstance(obj, int) or (np is not None and isinstance(obj, np.integer)):  # an IntEnum too: a code stays its number
        return int(obj)
    if isinstance(obj, enum.Enum):
        return obj.name
    if isinstance(obj, float) or (np is not None and isinstance(obj, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if np is not None and isinstance(obj, np.ndarray):
        return [jsonable(v) for v in obj.tolist()]
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [jsonable(v) for v in obj]
    return str(obj)


def dumps(obj: Any, *, indent: int | None = None, sort_keys: bool = False) -> str:
    """Strict JSON text of ``obj`` (see :func:`jsonable`)."""
    return json.dumps(jsonable(obj), indent=indent, sort_keys=sort_keys, allow_nan=False)


def print_json(obj: Any, *, indent: int | None = None, sort_keys: bool = False, file: IO[str] | None = None) -> None:
    """Print strict JSON of ``obj`` on one line (or indented) and flush. A reader that left
    (``hapticproxy status --json | head -c 10``) ends the output quietly: stdout is pointed at
    /dev/null so the interpreter's own flush at exit raises no second ``BrokenPipeError``."""
    out = sys.stdout if file is None else file
    try:
        print(dumps(obj, indent=indent, sort_keys=sort_keys), file=out, flush=True)
    except BrokenPipeError:
        if out is sys.stdout:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
