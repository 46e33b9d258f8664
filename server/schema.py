"""Config tables as typed msgspec Structs: one declaration per table, converted once at the
boundary, errors in the project's words.

A table is declared as a ``msgspec.Struct`` (``forbid_unknown_fields=True``) whose fields carry
their type, default and bounds (``Annotated[float, Meta(ge=..., le=..., description=...)]``).
:func:`convert` turns a plain table (TOML, a dict) into that Struct and, when msgspec refuses
it, rewrites the refusal as ``fail(key, reason)`` with the dotted key and a reason written for
the person who edits the file::

    loop.rate_hz: must be >= 100, got 50
    loop.rtae_hz: unknown key (did you mean 'rate_hz'?); known: cpu, rate_hz, realtime, spin_us
    device.inertia_kg_m2: does not apply to a 1dof device

msgspec checks types, bounds and unknown keys; the reasons are derived from the same
declaration (``msgspec.inspect``), so a bound is written once. Values must also be finite
(TOML allows ``inf`` and ``nan``; msgspec would keep them where a field has no bound).
:func:`to_toml` renders the effective values back (``serve --print-config``), with each key's
``description`` as a comment.
"""
from __future__ import annotations

import difflib
import json
import math
import re
from typing import Any, Callable, Iterable

import msgspec
from msgspec import inspect as mi

Fail = Callable[[str, str], Exception]

_AT = re.compile(r"^(?P<msg>.*?)(?: - at `\$(?P<path>[^`]*)`)?$", re.S)
_UNKNOWN = re.compile(r"^Object contains unknown field `(?P<name>[^`]*)`")
_MISSING = re.compile(r"^Object missing required field `(?P<name>[^`]*)`")
_SEG = re.compile(r"\.([^.\[]+)|\[(\d+)\]")


def plain(obj: Any) -> Any:
    """Numpy scalars and arrays (and tuples) -> Python builtins, so a table built in code
    converts like one read from TOML."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    tolist = getattr(obj, "tolist", None)
    if tolist is not None and type(obj).__module__ == "numpy":
        return plain(tolist())
    return obj


def unknown_key(key: str, options: Iterable[str], fail: Fail) -> Exception:
    """``key: unknown key (did you mean 'x'?); known: ...``"""
    options = sorted(options)
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], options, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return fail(key, f"unknown key{hint}; known: {', '.join(options)}")


def _join(prefix: str, path: str) -> str:
    out = prefix
    for name, index in _SEG.findall(path):
        out = f"{out}[{index}]" if name == "" else (f"{out}.{name}" if out else name)
    return out


def _segments(path: str) -> list[str | int]:
    return [int(i) if n == "" else n for n, i in _SEG.findall(path)]


def _strip(t):
    while isinstance(t, mi.Metadata):
        t = t.type
    return t


def _kind_of(v) -> str:
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, (int, float)):
        return "number"
    if isinstance(v, str):
        return "str"
    if isinstance(v, (list, tuple)):
        return "list"
    if isinstance(v, dict):
        return "table"
    return "other"


def _kind_of_type(t) -> str:
    t = _strip(t)
    if isinstance(t, (mi.FloatType, mi.IntType)):
        return "number"
    if isinstance(t, mi.BoolType):
        return "bool"
    if isinstance(t, (mi.StrType, mi.LiteralType)):
        return "str"
    if isinstance(t, (mi.ListType, mi.TupleType, mi.VarTupleType)):
        return "list"
    if isinstance(t, (mi.StructType, mi.DictType)):
        return "table"
    return "other"


_WORDS = {"number": "a number", "bool": "true or false", "str": "a string", "list": "a list", "table": "a table"}


def _what(t) -> str:
    t = _strip(t)
    if isinstance(t, mi.IntType):
        return "an integer"
    if isinstance(t, mi.LiteralType):
        return " or ".join(repr(v) for v in t.values)
    if isinstance(t, (mi.ListType, mi.VarTupleType)) and _kind_of_type(t.item_type) == "number":
        return "a list of numbers"
    return _WORDS.get(_kind_of_type(t), "a value")


def _bounds(t, v) -> str | None:
    if t.ge is not None and not v >= t.ge:
        return f"must be >= {t.ge:g}, got {v!r}"
    if t.gt is not None and not v > t.gt:
        return f"must be > {t.gt:g}, got {v!r}"
    if t.le is not None and not v <= t.le:
        return f"must be <= {t.le:g}, got {v!r}"
    if t.lt is not None and not v < t.lt:
        return f"must be < {t.lt:g}, got {v!r}"
    return None


def reason(t, v) -> str | None:
    """Why value ``v`` does not fit the (inspected) type ``t``; None if it fits at this level."""
    t = _strip(t)
    if isinstance(t, (mi.FloatType, mi.IntType)):
        integer = isinstance(t, mi.IntType)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return f"expected {'an integer' if integer else 'a number'}, got {v!r}"
        if integer and not isinstance(v, int):
            return f"expected an integer, got {v!r}"
        if not math.isfinite(v):
            return f"must be finite, got {v!r}"
        return _bounds(t, v)
    if isinstance(t, mi.BoolType):
        return None if isinstance(v, bool) else f"expected true or false, got {v!r}"
    if isinstance(t, mi.StrType):
        if not isinstance(v, str):
            return f"expected a string, got {v!r}"
        if t.min_length is not None and len(v) < t.min_length:
            return "must not be empty" if t.min_length == 1 else f"expected at least {t.min_length} characters"
        return None
    if isinstance(t, mi.LiteralType):
        if v in t.values and type(v) in {type(x) for x in t.values}:
            return None
        options = ", ".join(str(x) if x != "" else '""' for x in t.values)
        return f"expected one of {options}; got {v!r}"
    if isinstance(t, (mi.StructType, mi.DictType)):
        return None if isinstance(v, dict) else f"expected a table, got {v!r}"
    if isinstance(t, mi.TupleType):
        n = len(t.item_types)
        if not isinstance(v, (list, tuple)) or len(v) != n:
            things = "numbers" if all(_kind_of_type(x) == "number" for x in t.item_types) else "values"
            return f"expected {n} {things}, got {v!r}"
        return None
    if isinstance(t, (mi.ListType, mi.VarTupleType)):
        if not isinstance(v, (list, tuple)):
            return f"expected a list, got {v!r}"
        if t.min_length is not None and len(v) < t.min_length:
            return "must not be empty" if t.min_length == 1 else f"expected at least {t.min_length} items, got {len(v)}"
        if t.max_length is not None and len(v) > t.max_length:
            return f"expected at most {t.max_length} items, got {len(v)}"
        return None
    if isinstance(t, mi.UnionType):
        members = [m for m in t.types if not isinstance(_strip(m), mi.NoneType)]
        if v is None and len(members) < len(t.types):
            return None
        same = [m for m in members if _kind_of_type(m) == _kind_of(v)]
        for m in same:
            if reason(m, v) is None:
                return None
        if len(same) == 1 and not isinstance(_strip(same[0]), mi.LiteralType):
            return reason(same[0], v)
        return f"expected {' or '.join(_what(m) for m in members)}, got {v!r}"
    return None


def _member_for(t, v):
    """The union member a value was meant for (the one of its kind)."""
    t = _strip(t)
    if isinstance(t, mi.UnionType):
        for m in t.types:
            if _kind_of_type(m) == _kind_of(v) and reason(m, v) is None:
                return _strip(m)
        for m in t.types:
            if _kind_of_type(m) == _kind_of(v):
                return _strip(m)
    return t


def _walk(t, raw, segs):
    """The inspected type and the raw value at ``segs`` (None where the path leaves them)."""
    for s in segs:
        t = _member_for(t, raw)
        if isinstance(t, mi.StructType) and isinstance(s, str):
            f = next((f for f in t.fields if f.encode_name == s), None)
            t = f.type if f is not None else None
            raw = raw.get(s) if isinstance(raw, dict) else None
        elif isinstance(t, mi.DictType) and isinstance(s, str):
            t, raw = t.value_type, raw.get(s) if isinstance(raw, dict) else None
        elif isinstance(t, (mi.ListType, mi.VarTupleType)) and isinstance(s, int):
            t, raw = t.item_type, raw[s] if isinstance(raw, (list, tuple)) and s < len(raw) else None
        elif isinstance(t, mi.TupleType) and isinstance(s, int):
            t = t.item_types[s] if s < len(t.item_types) else None
            raw = raw[s] if isinstance(raw, (list, tuple)) and s < len(raw) else None
        else:
            return None, None
        if t is None:
            return None, None
    return _strip(t), raw


def field_names(cls) -> list[str]:
    return [f.encode_name for f in mi.type_info(cls).fields]


def convert(cls, raw, *, prefix: str, fail: Fail, siblings: dict[str, type] | None = None, kind: str = ""):
    """``raw`` (a dict) -> an instance of the Struct ``cls``; a refusal -> ``fail(key, reason)``.

    ``siblings``: other Structs of the same family (e.g. the other device kinds) by name: a key
    that one of them has but ``cls`` lacks "does not apply to a {kind} ..." instead of unknown.
    """
    raw = plain(raw)
    if not isinstance(raw, dict):
        raise fail(prefix, f"expected a table, got {raw!r}")
    try:
        obj = msgspec.convert(raw, cls, strict=True)
    except msgspec.ValidationError as exc:
        raise _translate(cls, raw, str(exc), prefix, fail, siblings or {}, kind) from None
    _finite(raw, prefix, fail)
    return obj


def _translate(cls, raw, text: str, prefix: str, fail: Fail, siblings, kind: str) -> Exception:
    m = _AT.match(text)
    msg, path = m.group("msg"), m.group("path") or ""
    segs = _segments(path)
    where = _join(prefix, path)
    t, v = _walk(mi.type_info(cls), raw, segs)
    u = _UNKNOWN.match(msg)
    if u:
        name = u.group("name")
        key = f"{where}.{name}" if where else name
        options = [f.encode_name for f in t.fields] if isinstance(t, mi.StructType) else []
        if not segs and any(name in field_names(s) for s in siblings.values()):
            return fail(key, f"does not apply to a {kind} device" if kind else "does not apply here")
        return unknown_key(key, options, fail)
    r = _MISSING.match(msg)
    if r:
        return fail(f"{where}.{r.group('name')}" if where else r.group("name"), "required")
    why = reason(t, v) if t is not None else None
    return fail(where, why or msg[0].lower() + msg[1:])


def _finite(obj, key: str, fail: Fail) -> None:
    if isinstance(obj, float) and not math.isfinite(obj):
        raise fail(key, f"must be finite, got {obj!r}")
    if isinstance(obj, dict):
        for k, v in obj.items():
            _finite(v, f"{key}.{k}" if key else str(k), fail)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _finite(v, f"{key}[{i}]", fail)


def builtins(obj) -> Any:
    """A Struct (nested) -> plain dicts and lists, every field written out (defaults too)."""
    return plain(msgspec.to_builtins(obj))


def descriptions(cls, prefix: str = "") -> dict[str, str]:
    """Dotted key -> the field's ``Meta(description=...)``, for the Struct and nested Structs."""
    out: dict[str, str] = {}
    for f in mi.type_info(cls).fields:
        key = f"{prefix}{f.encode_name}"
        t = f.type
        if isinstance(t, mi.Metadata) and t.extra_json_schema and "description" in t.extra_json_schema:
            out[key] = t.extra_json_schema["description"]
        s = _strip(t)
        if isinstance(s, mi.StructType):
            out.update(descriptions(s.cls, key + "."))
    return out


# ------------------------------------------------------------------------------------ TOML
def _val(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v == math.inf else ("-inf" if v == -math.inf else repr(v)))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_val(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_bare(k)} = {_val(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} as TOML: {v!r}")


def _bare(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def to_toml(data: dict, docs: dict[str, str] | None = None) -> str:
    """A nested dict -> TOML: scalars first, then one ``[table]`` per nested dict (depth first),
    each key followed by its description as a comment when ``docs`` has it."""
    docs = docs or {}
    lines: list[str] = []

    def table(body: dict, path: str) -> None:
        for k, v in body.items():
            if isinstance(v, dict):
                continue
            key = f"{path}.{k}" if path else k
            doc = docs.get(key)
            lines.append(f"{_bare(k)} = {_val(v)}" + (f"  # {doc}" if doc else ""))
        for k, v in body.items():
            if isinstance(v, dict):
                key = f"{path}.{k}" if path else k
                lines.append("")
                lines.append(f"[{'.'.join(_bare(p) for p in key.split('.'))}]")
                table(v, key)

    table(data, "")
    return "\n".join(lines) + "\n"
