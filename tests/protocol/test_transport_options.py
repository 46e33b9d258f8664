"""Transport options: declared once, by each backend's constructor; parsed without opening anything."""
import inspect

import pytest

from hapticproxy.protocol.transport import (
    MemTransport, UdpTransport, transport_option_types, transport_options,
)


def test_the_options_are_the_backends_keyword_parameters():
    from hapticproxy.protocol.transport.zenoh_backend import ZenohTransport

    for scheme, cls in (("mem", MemTransport), ("udp", UdpTransport), ("zenoh", ZenohTransport)):
        params = inspect.signature(cls.__init__).parameters
        opts = transport_option_types(scheme)
        assert set(opts) == set(params) - {"self", "host", "port", "name", "session", "role"}
        assert all(opts[k][1] == params[k].default for k in opts)


def test_options_are_converted_and_checked_without_opening():
    parsed, opts = transport_options("zenoh://127.0.0.1:7447/lab?mode=client&ring_capacity=8&express=0",
                                     connect_timeout_s="2.5")
    assert parsed.name == "lab" and opts == {"mode": "client", "ring_capacity": 8, "express": False,
                                             "connect_timeout_s": 2.5}
    _, opts = transport_options({"url": "udp://127.0.0.1:0?rcvbuf_bytes=1024", "rcvbuf_bytes": 4096})
    assert opts == {"rcvbuf_bytes": 4096}                 # the mapping wins over the query
    with pytest.raises(ValueError, match=r"unknown option 'rcvbuf' for udp transport \(did you mean 'rcvbuf_bytes'\?\)"):
        transport_options("udp://127.0.0.1:0?rcvbuf=1")
    for bad in ("ring_capacity=2.5", "ring_capacity=many", "express=maybe"):
        with pytest.raises(ValueError, match="has a bad value"):
            transport_options(f"zenoh://127.0.0.1:7447/lab?{bad}")
    with pytest.raises(ValueError, match="has a bad value True"):
        transport_options("mem://x", queue_capacity=True)
