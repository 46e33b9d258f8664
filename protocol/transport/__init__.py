"""Datagram transports for protocol v1: one small interface, three backends.

Open an endpoint with :func:`open_transport`::

    server = open_transport("udp://127.0.0.1:0", role="server")
    client = open_transport(server.url, role="client")
    client.send(update_bytes)
    nbytes, peer = server.recv_into(buf)       # (0, None) at once when nothing is waiting
    server.send(ack_bytes, peer)

URL formats (options may also be given as a mapping or as keyword arguments; keyword arguments
win over mapping entries, which win over URL query parameters; unknown options raise
``ValueError`` naming them). A backend's options are its constructor's keyword parameters
(:func:`transport_option_types`: one declaration, the constructor's signature);
:func:`transport_options` parses and converts them without opening anything:

``mem://NAME``
    In-process bus for tests (:class:`~.mem.MemTransport`). Options: ``max_packet_bytes``,
    ``queue_capacity``. Open the server before its clients.
``udp://HOST:PORT``
    Server: bind ``HOST:PORT`` (``PORT`` 0 = any free port, see ``.url``). Client: connect to the
    server at ``HOST:PORT`` (:class:`~.udp.UdpTransport`). IPv6 hosts in brackets
    (``udp://[::1]:9000``). Options: ``max_packet_bytes``, ``rcvbuf_bytes``, ``sndbuf_bytes``.
``zenoh://HOST:PORT/SESSION``
    Zenoh 1.x (:class:`~.zenoh_backend.ZenohTransport`), key expressions ``hapticproxy/SESSION/...``.
    Default ``mode=peer``: the server listens on ``tcp/HOST:PORT`` and the client connects
    there directly, multicast scouting off (the embedded, loopback default; ``PORT`` 0 = pick a
    free port for the server, see ``.url``). ``mode=client``: both sides connect as Zenoh
    clients to a router at ``HOST:PORT`` (multi-machine set-ups). Options: ``mode``
    (``peer``/``client``), ``protocol`` (link protocol, default ``tcp``; ``tls`` with a TLS
    config), ``config`` (path of a Zenoh JSON5 config file used as the base, e.g. one from
    ``deploy/zenoh/``), ``max_packet_bytes``, ``ring_capacity``, ``connect_timeout_s``,
    ``express``, ``lowlatency`` (both ends must agree).

The ``zenoh`` package is imported only when a ``zenoh://`` endpoint is opened, so the rest of
the protocol package needs only the standard library.

Backends are found by scheme in :data:`TRANSPORT_REGISTRY`: the built-ins (:data:`TRANSPORTS`)
merged with the ``hapticproxy.transports`` entry-point group, so a lab's package adds a scheme
from its own ``pyproject.toml`` (``[project.entry-points."hapticproxy.transports"] shm =
"mylab.shm:ShmTransport"``, a :class:`Transport` subclass whose ``url_form`` says what its URL
holds and whose constructor takes ``role`` and those of ``host``, ``port``, ``name`` it needs);
``hapticproxy plugins`` lists them.
"""
from __future__ import annotations

import difflib
import inspect
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, unquote, urlsplit

from .base import (
    DEFAULT_DRAIN_MAX_PACKETS,
    DEFAULT_MAX_PACKET_BYTES,
    MAX_DATAGRAM_BYTES,
    Peer,
    Transport,
    TransportClosedError,
    TransportCounters,
    TransportError,
)
from ..registry import Registry
from .mem import MemTransport
from .udp import UdpTransport

__all__ = [
    "DEFAULT_DRAIN_MAX_PACKETS",
    "DEFAULT_MAX_PACKET_BYTES",
    "MAX_DATAGRAM_BYTES",
    "MemTransport",
    "Peer",
    "SCHEMES",
    "TRANSPORTS",
    "TRANSPORT_REGISTRY",
    "Transport",
    "TransportClosedError",
    "TransportCounters",
    "TransportError",
    "TransportUrl",
    "UdpTransport",
    "open_transport",
    "parse_transport_url",
    "transport_option_types",
    "transport_options",
]

#: the built-in backends by URL scheme (scheme -> module:class)
TRANSPORTS = {
    "mem": "hapticproxy.protocol.transport.mem:MemTransport",
    "udp": "hapticproxy.protocol.transport.udp:UdpTransport",
    # the module imports zenoh only when a ZenohTransport is built
    "zenoh": "hapticproxy.protocol.transport.zenoh_backend:ZenohTransport",
}
#: the built-in schemes
SCHEMES = tuple(TRANSPORTS)
URL_FORMS = ("host:port/name", "host:port", "name")


def _is_transport(name: str, obj) -> str:
    if not (isinstance(obj, type) and issubclass(obj, Transport)):
        return "is not a Transport subclass"
    if getattr(obj, "url_form", None) not in URL_FORMS:
        return f"has url_form {getattr(obj, 'url_form', None)!r}, not one of {', '.join(URL_FORMS)}"
    return ""


#: transport backends by URL scheme: :data:`TRANSPORTS` merged with the ``hapticproxy.transports``
#: entry points (:mod:`hapticproxy.protocol.registry`)
TRANSPORT_REGISTRY = Registry("transport", "hapticproxy.transports", TRANSPORTS, check=_is_transport)


def _int(value: Any) -> int:
    if isinstance(value, bool):
        raise ValueError
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str):
        return int(value.strip())
    raise ValueError


def _bool(value: Any) -> bool:
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("1", "true", "yes", "on"):
        return True
    if text in ("0", "false", "no", "off"):
        return False
    raise ValueError


def _float(value: Any) -> float:
    if isinstance(value, bool):
        raise ValueError
    return float(value)


def _str(value: Any) -> str:
    if not isinstance(value, (str, int, float)) or isinstance(value, bool):
        raise ValueError
    return str(value)


#: annotation of a backend's keyword parameter -> (converter from a URL string or a value, what it wants)
_CONVERTERS = {"int": (_int, "an integer"), "float": (_float, "a number"), "bool": (_bool, "true or false"),
               "str": (_str, "a string")}
#: the backends' parameters that come from the URL itself or from ``open_transport``'s arguments
_NOT_OPTIONS = ("self", "host", "port", "name", "session", "role")


def _unknown_scheme(scheme: str, url: str = "") -> ValueError:
    return ValueError(f"transport url scheme must be one of {', '.join(TRANSPORT_REGISTRY.names())}; got {scheme!r}"
                      + (f" in {url!r}" if url else ""))


def _backend(scheme: str) -> type:
    """The backend class of ``scheme``; ``ValueError`` naming the schemes when there is none."""
    if not TRANSPORT_REGISTRY.known(scheme):
        raise _unknown_scheme(scheme)
    return TRANSPORT_REGISTRY.load(scheme)


def transport_option_types(scheme: str) -> dict[str, tuple[Any, Any, str]]:
    """A scheme's options: ``name -> (converter, default, what it wants)``. Declared once, by the
    backend's constructor (its keyword parameters, their annotations and defaults)."""
    out: dict[str, tuple[Any, Any, str]] = {}
    for name, p in inspect.signature(_backend(scheme).__init__).parameters.items():
        if name in _NOT_OPTIONS or p.kind not in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
            continue
        ann = p.annotation if isinstance(p.annotation, str) else getattr(p.annotation, "__name__", str(p.annotation))
        base = next(t.strip() for t in ann.split("|") if t.strip() != "None")
        conv, what = _CONVERTERS[base]
        out[name] = (conv, p.default, what)
    return out


@dataclass(frozen=True)
class TransportUrl:
    """A parsed transport URL: ``scheme``, ``host``, ``port``, ``name`` and query ``options``.

    ``name`` is the mem bus name or the zenoh session name (URL path); ``host``/``port`` are
    empty/0 for ``mem``.
    """

    scheme: str
    host: str = ""
    port: int = 0
    name: str = ""
    options: dict[str, str] = field(default_factory=dict)


def parse_transport_url(url: str) -> TransportUrl:
    """Parse a transport URL (see the module docstring); ``ValueError`` if malformed."""
    if not isinstance(url, str) or "://" not in url:
        raise ValueError(f"transport url must look like 'scheme://...', got {url!r}")
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if not TRANSPORT_REGISTRY.known(scheme):
        raise _unknown_scheme(scheme, url)
    form = getattr(_backend(scheme), "url_form", "host:port/name")
    options: dict[str, str] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False):
        if key in options:
            raise ValueError(f"transport url option {key!r} given twice in {url!r}")
        options[key] = value
    if form == "name":
        name = unquote(parts.netloc + parts.path)
        if not name:
            raise ValueError(f"{scheme} url needs a name: '{scheme}://NAME', got {url!r}")
        return TransportUrl(scheme, name=name, options=options)
    try:
        host = parts.hostname or ""
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"bad host:port in transport url {url!r}: {exc}") from None
    if not host or port is None:
        raise ValueError(f"{scheme} url needs HOST:PORT, e.g. '{scheme}://127.0.0.1:7447', got {url!r}")
    name = unquote(parts.path.lstrip("/"))
    if form == "host:port" and name:
        raise ValueError(f"{scheme} url takes no path, got {parts.path!r} in {url!r}")
    return TransportUrl(scheme, host=host, port=port, name=name, options=options)


def transport_options(url_or_config: str | Mapping[str, Any], **options: Any) -> tuple[TransportUrl, dict[str, Any]]:
    """Parse a transport URL (or a mapping with ``"url"``) and its options without opening
    anything: ``(parsed url, converted options)``. Keyword arguments win over mapping entries,
    which win over URL query parameters. ``ValueError`` naming the option when one is unknown or
    has a bad value (what a config loader calls to refuse a bad URL at start)."""
    if isinstance(url_or_config, str):
        url, config = url_or_config, {}
    elif isinstance(url_or_config, Mapping):
        if "url" not in url_or_config:
            raise ValueError("transport config mapping needs a 'url' key")
        config = dict(url_or_config)
        url = config.pop("url")
    else:
        raise ValueError(f"url_or_config must be a URL string or a mapping, got {type(url_or_config).__name__}")
    parsed = parse_transport_url(url)
    allowed = transport_option_types(parsed.scheme)
    merged: dict[str, Any] = {}
    for source in (parsed.options, config, options):
        for key, value in source.items():
            if key not in allowed:
                close = difflib.get_close_matches(str(key), list(allowed), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ValueError(f"unknown option {key!r} for {parsed.scheme} transport{hint}; "
                                 f"allowed: {', '.join(sorted(allowed))}")
            conv, default, what = allowed[key]
            if value is None and default is None:
                merged[key] = None
                continue
            try:
                merged[key] = conv(value)
            except (TypeError, ValueError):
                raise ValueError(f"option {key!r} has a bad value {value!r} (expected {what})") from None
    return parsed, merged


def open_transport(url_or_config: str | Mapping[str, Any], role: str = "server", **options: Any) -> Transport:
    """Open a transport endpoint.

    Args:
        url_or_config: a URL string (formats in the module docstring) or a mapping with a
            ``"url"`` key plus option keys, e.g. ``{"url": "udp://127.0.0.1:0", "rcvbuf_bytes":
            65536}`` (what a config file would hold).
        role: ``"server"`` (listens, many peers) or ``"client"`` (one peer, the server).
        **options: backend options, overriding those of the mapping and of the URL query.

    Raises:
        ValueError: malformed URL, unknown option or bad option value (the message names it).
        TransportError: the endpoint could not be set up (name taken, no server, Zenoh peer
            not reachable within ``connect_timeout_s``).
        OSError: the socket could not be bound/connected (e.g. port in use).
    """
    if role not in ("server", "client"):
        raise ValueError(f"role must be 'server' or 'client', got {role!r}")
    parsed, kwargs = transport_options(url_or_config, **options)
    cls = _backend(parsed.scheme)
    params = inspect.signature(cls.__init__).parameters
    where = {"host": parsed.host, "port": parsed.port}
    if parsed.name:  # the mem bus, or the zenoh session (its constructor's default when empty)
        where["name" if "name" in params else "session"] = parsed.name
    return cls(role=role, **{k: v for k, v in where.items() if k in params}, **kwargs)
