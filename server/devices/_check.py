"""Config checking for the device drivers: every error is ``ValueError("device.<key>: <reason>")``.

A driver declares its ``[device]`` table as msgspec Structs (one per kind, see ``sim.py``,
``remote.py``, ``hands.py``); :func:`convert` turns a table into one (types, bounds, unknown
keys, with the dotted key and a did-you-mean hint: ``server/schema.py``). What a type cannot
say (lengths that depend on the kind, unit vectors, the workspace) is checked by the helpers
below, on the converted values.

Reduced coordinates: a kind's own coordinates, written in config as a short list, expanded here
to the world 6-vectors (x y z rx ry rz or fx fy fz tx ty tz) the kernels use:

- ``1dof``: ``[s]`` (or a bare number) along the unit axis: a vector ``s * axis``, a pose
  ``origin_m + s * axis``;
- ``planar``: ``[x, y, theta]`` -> ``(x, y, 0, 0, 0, theta)``;
- ``spatial``: ``[x, y, z, rx, ry, rz]`` (rotation vector, rad); a pose may also be given as
  ``[x, y, z, qw, qx, qy, qz]``.

A full 6-vector is accepted for every kind (components the kind cannot move in are ignored).
"""
from __future__ import annotations

import math

import numpy as np

from .. import schema

REDUCED_DIMS = {"1dof": 1, "planar": 3, "spatial": 6}
#: where the reduced components sit in the 6-vector (1dof: along the axis, see ``vector6``)
PLANAR_SLOTS = (0, 1, 5)


def fail(key: str, reason: str) -> ValueError:
    return ValueError(f"{key}: {reason}")


def convert(cls, cfg, prefix: str = "device", *, siblings: dict | None = None, kind: str = ""):
    """A table -> the Struct ``cls``; refusals as ``ValueError("<prefix>.<key>: <reason>")``."""
    return schema.convert(cls, cfg, prefix=prefix, fail=fail, siblings=siblings, kind=kind)


def table(obj, first=("driver", "kind"), last=("hand",)) -> dict:
    """A converted table as a plain dict (every key), ``first`` keys first and ``last`` last."""
    d = schema.builtins(obj)
    out = {k: d[k] for k in first if k in d}
    out.update((k, v) for k, v in d.items() if k not in first and k not in last)
    out.update((k, d[k]) for k in last if k in d)
    return out


def num(key: str, v, *, lo=None, hi=None, lo_open=False, hi_open=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise fail(key, f"expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise fail(key, f"must be finite, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise fail(key, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and (v >= hi if hi_open else v > hi):
        raise fail(key, f"must be {'<' if hi_open else '<='} {hi:g}, got {v:g}")
    return v


def numbers(key: str, v, lengths) -> np.ndarray:
    """A flat list of finite numbers whose length is one of ``lengths`` (a bare number = [v])."""
    if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
        v = [v]
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if not isinstance(v, (list, tuple)):
        raise fail(key, f"expected a list of {' or '.join(map(str, lengths))} numbers, got {v!r}")
    if len(v) not in lengths:
        raise fail(key, f"expected {' or '.join(map(str, lengths))} numbers, got {len(v)}")
    return np.array([num(f"{key}[{i}]", x) for i, x in enumerate(v)], dtype=np.float64)


def rotvec_from_quat(key: str, q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-6:
        raise fail(key, f"quaternion (qw qx qy qz) must be unit, |q| = {n:.9g}")
    q = q / n
    if q[0] < 0:
        q = -q
    s = float(np.linalg.norm(q[1:]))
    if s < 1e-12:
        return 2.0 * q[1:]
    return (2.0 * math.atan2(s, q[0]) / s) * q[1:]


def vector6(key: str, v, kind: str, axis: np.ndarray) -> np.ndarray:
    """A wrench, displacement or twist in reduced coordinates (or a full 6-vector) -> world 6."""
    r = REDUCED_DIMS[kind]
    a = numbers(key, v, sorted({r, 6}))
    if len(a) == 6:
        return a
    out = np.zeros(6)
    if kind == "1dof":
        out[:3] = a[0] * axis
    else:
        out[list(PLANAR_SLOTS)] = a
    return out


def pose6(key: str, v, kind: str, axis: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """A pose in reduced coordinates (spatial: also x y z qw qx qy qz) -> x y z rx ry rz."""
    r = REDUCED_DIMS[kind]
    lengths = sorted({r, 6} | ({7} if kind == "spatial" else set()))
    a = numbers(key, v, lengths)
    if len(a) == 7:
        return np.concatenate([a[:3], rotvec_from_quat(key, a[3:])])
    if len(a) == 6:
        return a
    out = np.zeros(6)
    if kind == "1dof":
        out[:3] = origin + a[0] * axis
    else:
        out[list(PLANAR_SLOTS)] = a
    return out


def placed6(key: str, v, kind: str) -> np.ndarray:
    """A per-component parameter (frequency, phase): a number for all, or one per reduced
    coordinate (or 6), placed in the matching 6-vector slots (1dof: x, y and z)."""
    r = REDUCED_DIMS[kind]
    a = numbers(key, v, sorted({1, r, 6}))
    if len(a) == 1:
        return np.full(6, a[0])
    if len(a) == 6:
        return a
    out = np.zeros(6)
    out[list(PLANAR_SLOTS)] = a
    return out


def string(key: str, v, choices=None) -> str:
    if not isinstance(v, str):
        raise fail(key, f"expected a string, got {v!r}")
    if choices is not None and v not in choices:
        raise fail(key, f"expected one of {', '.join(choices)}; got {v!r}")
    return v
