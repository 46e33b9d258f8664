"""Haply Inverse3 (entry point ``haply``): over its USB serial port through PyPI
``haplyhardwareapi``, or through Haply's Inverse Service (its local websocket JSON protocol) as a
second transport of the same driver.

**Who owns the clock: the loop**, on both transports. Over serial, each ``write`` is one exchange
(``end_effector_force``: the force goes out, the device answers its position and velocity);
``read`` hands the loop the state of the last exchange (one period old). The Inverse Service
answers exactly one state frame per message it gets (a wireless VerseGrip it lists gives the
handle's orientation and buttons: 6 DOF sensed, 3 rendered), so the client, here the loop, sets the rate.
The Inverse3 renders the last force it was sent until the next one and no firmware watchdog is
documented for it: the driver's watchdog is the host's (``watchdog_s``, on the loop's clock): a
stall of the host leaves the last force on until the loop runs again, which then cuts it.
:attr:`HaplyDevice.native` keeps the ``Inverse3`` object and its ``SerialStream`` (the package
segfaults when the stream is dropped while the device object lives) or the websocket.

Quirks of ``haplyhardwareapi`` 0.1.13 this driver works around (found running it on the fake):

- ``SerialStream(path)`` on a missing port does not raise, and ``device_wakeup_dict()`` then
  returns uninitialised memory (a random device id, model and version, a zero UUID): the driver
  checks the path itself and takes a zero UUID as "nothing answered";
- a call whose reply times out (``Inverse3(stream, timeout)``, 5 s by default) prints two
  ``[err]`` lines to stderr and returns zeros (position and velocity all 0.0) instead of
  raising: the driver sets a short timeout (``timeout_s``) and takes an all-zero reply as a lost
  device (the handle is never exactly at the base's origin);
- after a garbled reply the next exchanges may read leftovers: ``enable()`` drains the input
  (``flush_input``) and wakes the device again before arming.

Config (``[device]``, ``driver = "haply"``):

``kind`` = ``"spatial"``
``transport`` = ``"serial"``
    ``serial`` (``port``) or ``service`` (``url``).
``port`` = ``""``
    The serial port (``/dev/ttyACM0``); required for ``serial`` (``auto``: the first port
    ``detect_inverse3s()`` finds by USB vendor id).
``url`` = ``"ws://127.0.0.1:10001"``
    The Inverse Service's websocket.
``device_id`` = 0
    The device to use (the wake-up's device id, the service's ``device_id``); 0: the first.
``max_force_n`` = 3.0
    The force cap: Haply's rated figure was not available to this project, so it is the
    config's (raise it knowingly).
``timeout_s`` = 0.005
    How long one exchange may take before the device counts as lost.
``watchdog_s`` = 0.05, ``max_speed_m_per_s`` = 2.0
``workspace_min_m`` / ``workspace_max_m`` = +-0.2 m
"""
from __future__ import annotations

import importlib.util
import json
import math
import os
import stat
from typing import Annotated, Literal

import msgspec
import numpy as np
from msgspec import Meta

from . import _check as ck
from . import models
from .base import DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_OK, DS_BUTTONS, DS_GRIPPER, DS_GRIPPER_RATE, DeviceInfo
from .vendor import DeviceUnavailable, VendorDevice, missing

UDEV_RULE = "deploy/udev/99-hapticproxy.rules"


class HaplyConfig(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    driver: str = "haply"
    kind: str = "spatial"
    transport: Literal["serial", "service"] = "serial"
    port: str = ""
    url: str = "ws://127.0.0.1:10001"
    device_id: Annotated[int, Meta(ge=0, le=65535)] = 0
    max_force_n: Annotated[float, Meta(gt=0.0, le=50.0)] = 3.0
    timeout_s: Annotated[float, Meta(gt=0.0, le=5.0)] = 0.005
    watchdog_s: Annotated[float, Meta(ge=0.0, le=10.0)] = 0.05
    max_speed_m_per_s: Annotated[float, Meta(gt=0.0, le=100.0)] = 2.0
    workspace_min_m: list[float] = msgspec.field(default_factory=lambda: [-0.2, -0.2, -0.2])
    workspace_max_m: list[float] = msgspec.field(default_factory=lambda: [0.2, 0.2, 0.2])


def parse_config(config: dict | None) -> HaplyConfig:
    c = ck.convert(HaplyConfig, dict(config or {}), "device")
    if c.kind != "spatial":
        raise ck.fail("device.kind", f"an Inverse3 is spatial (it moves in 3-D), got {c.kind!r}")
    if c.transport == "serial" and not c.port:
        raise ck.fail("device.port", "the serial transport needs the port (e.g. port = \"/dev/ttyACM0\", "
                      "or \"auto\"; `hapticproxy devices` lists what is connected)")
    lo = ck.numbers("device.workspace_min_m", c.workspace_min_m, (3,))
    hi = ck.numbers("device.workspace_max_m", c.workspace_max_m, (3,))
    if not np.all(hi > lo):
        raise ck.fail("device.workspace_max_m", "must exceed workspace_min_m on every axis")
    return c


def effective_config(config: dict, *, period_s: float) -> dict:
    return ck.table(parse_config(config))


def check_port(path: str) -> None:
    """The serial port exists and this user may open it; else the one line with the fix."""
    if not os.path.exists(path):
        raise DeviceUnavailable(f"device.port: {path} does not exist: is the Inverse3 plugged in and powered? "
                                f"(`hapticproxy devices` lists the ports that are there)")
    if not stat.S_ISCHR(os.stat(path).st_mode):
        raise DeviceUnavailable(f"device.port: {path} is not a serial device")
    if not os.access(path, os.R_OK | os.W_OK):
        raise DeviceUnavailable(f"device.port: permission denied on {path}: install the udev rule "
                                f"(sudo cp {UDEV_RULE} /etc/udev/rules.d/ && sudo udevadm control --reload-rules "
                                f"&& sudo udevadm trigger), or add your user to the group that owns {path} "
                                f"(ls -l {path}), then log in again")


class HaplyDevice(VendorDevice):
    """An Inverse3 over its serial port or the Inverse Service (see the module docstring)."""

    name = "haply"

    def __init__(self, config: dict, *, period_s: float, clock_ns=None) -> None:
        c = parse_config(config)
        self.config = c
        self._state = np.zeros(6)
        self._quat = np.array([1.0, 0.0, 0.0, 0.0])  # the VerseGrip's, where one is listed
        self._grip_id = None
        self.buttons = 0
        self._have = False
        self._f = [0.0, 0.0, 0.0]
        self.native = None
        if c.transport == "serial":
            ident = self._open_serial(c)
        else:
            ident = self._open_service(c)
        spec = models.INVERSE3
        grip = self._grip_id is not None
        info = DeviceInfo(
            model=spec.name + (" + VerseGrip" if grip else ""), vendor=spec.vendor, driver="haply",
            serial=str(ident.get("device_id", "")),
            sensed=("position", "rotation") if grip else spec.sensed, actuated=spec.actuated, max_force_n=c.max_force_n,
            workspace_radius_m=None, workspace_min_m=tuple(c.workspace_min_m), workspace_max_m=tuple(c.workspace_max_m),
            native_rate_hz=None, buttons=3 if grip else 0, calibration="not needed", clock="loop", sdk_units="m, N",
            source=f"device id and versions from the device ({c.transport}); force cap from the config "
                   f"(Haply's rated figures not available)")
        self.identity = ident
        limits = info.limits(max_speed_m_per_s=c.max_speed_m_per_s, watchdog_s=c.watchdog_s)
        super().__init__(info, limits, clock_ns=clock_ns)

    # -- serial -----------------------------------------------------------------------------
    def _open_serial(self, c: HaplyConfig) -> dict:
        if importlib.util.find_spec("HaplyHardwareAPI") is None:
            raise missing("haply", "haplyhardwareapi")
        import HaplyHardwareAPI as H  # noqa: N814

        port = c.port
        if port == "auto":
            found = list(H.detect_inverse3s())
            if not found:
                raise DeviceUnavailable("device.port: no Inverse3 found on /dev/ttyACM*, ttyUSB*, rfcomm* (plugged in "
                                        "and powered? permission: install " + UDEV_RULE + ")")
            port = found[0]
        check_port(port)
        self._stream = H.SerialStream(port)  # kept: the package segfaults if it goes first
        self._dev = H.Inverse3(self._stream, c.timeout_s)
        ident = self._wake(c)
        self.port = port
        self.native = {"inverse3": self._dev, "stream": self._stream, "port": port}
        self._exchange = self._serial_exchange
        return ident

    def _wake(self, c: HaplyConfig) -> dict:
        ident = dict(self._dev.device_wakeup_dict())
        if int(ident["device_id_ext"].int) == 0:
            raise DeviceUnavailable(f"device.port: nothing answered on {c.port} (is it an Inverse3? is another program "
                                    f"using it?)")
        if c.device_id and ident["device_id"] != c.device_id:
            raise DeviceUnavailable(f"device.device_id: the Inverse3 on {c.port} is {ident['device_id']}, "
                                    f"the config asks for {c.device_id}")
        ident["device_id_ext"] = str(ident["device_id_ext"])
        return ident

    def _serial_exchange(self, f) -> int:
        pos, vel = self._dev.end_effector_force(f)
        if not (any(pos) or any(vel)):
            return DEV_FAULT_LINK  # the package's reply to a timeout: zeros (see the docstring)
        s = self._state
        s[0], s[1], s[2] = pos
        s[3], s[4], s[5] = vel
        return DEV_OK

    # -- the Inverse Service ----------------------------------------------------------------
    def _open_service(self, c: HaplyConfig) -> dict:
        if importlib.util.find_spec("websockets") is None:
            raise missing("haply", "websockets")
        try:
            self._ws = _Websocket(c.url, c.timeout_s)
        except (OSError, TimeoutError) as exc:
            raise DeviceUnavailable(f"device.url: the Haply Inverse Service does not answer at {c.url} ({exc}): is "
                                    f"it running? (systemctl status haply-inverse-service)") from None
        try:
            inv = json.loads(self._ws.recv(timeout=2.0))
        except (TimeoutError, ValueError) as exc:
            self._ws.close()
            raise DeviceUnavailable(f"device.url: no inventory from the Inverse Service at {c.url} ({exc})") from None
        devs = inv.get("inverse3") or []
        if c.device_id:
            devs = [d for d in devs if _as_int(d.get("device_id")) == c.device_id]
        if not devs:
            self._ws.close()
            raise DeviceUnavailable(f"device.device_id: the Inverse Service at {c.url} has no Inverse3"
                                    + (f" with device_id {c.device_id}" if c.device_id else "")
                                    + f" (it lists {[d.get('device_id') for d in inv.get('inverse3') or []]})")
        self._ws_id = devs[0]["device_id"]
        self._take(devs[0])
        grips = inv.get("wireless_verse_grip") or []
        self._grip_id = grips[0].get("device_id") if grips else None
        if self._grip_id is not None:
            self._take_grip(grips[0])
        self.native = {"websocket": self._ws, "device_id": self._ws_id, "session_id": inv.get("session_id")}
        self._exchange = self._service_exchange
        return {"device_id": _as_int(self._ws_id), "session_id": inv.get("session_id")}

    def _take(self, d: dict) -> bool:
        st = d.get("state") or {}
        p, v = st.get("cursor_position"), st.get("cursor_velocity")
        if not p or not v:
            return False
        s = self._state
        s[0], s[1], s[2] = p["x"], p["y"], p["z"]
        s[3], s[4], s[5] = v["x"], v["y"], v["z"]
        return True

    def _take_grip(self, g: dict) -> None:
        st = g.get("state") or {}
        q = st.get("orientation")
        if q:
            n = math.sqrt(q["w"] ** 2 + q["x"] ** 2 + q["y"] ** 2 + q["z"] ** 2)
            if n > 0.0:
                self._quat[:] = (q["w"] / n, q["x"] / n, q["y"] / n, q["z"] / n)
        b = st.get("buttons") or {}
        self.buttons = int(bool(b.get("a"))) | int(bool(b.get("b"))) << 1 | int(bool(b.get("c"))) << 2

    def _service_exchange(self, f) -> int:
        msg = {"inverse3": [{"device_id": self._ws_id,
                             "commands": {"set_cursor_force": {"values": {"x": f[0], "y": f[1], "z": f[2]}}}}]}
        try:
            self._ws.send(json.dumps(msg))
            frame = json.loads(self._ws.recv(timeout=self.config.timeout_s))
        except TimeoutError:
            return DEV_FAULT_LINK
        except Exception:  # noqa: BLE001 - a closed socket, a malformed frame: the device is lost
            return DEV_FAULT_LINK
        if self._grip_id is not None:
            for g in frame.get("wireless_verse_grip") or []:
                if g.get("device_id") == self._grip_id:
                    self._take_grip(g)
        for d in frame.get("inverse3") or []:
            if d.get("device_id") == self._ws_id:
                return DEV_OK if self._take(d) else DEV_FAULT_HARDWARE
        return DEV_FAULT_LINK  # the service no longer lists the device: unplugged

    # -- VendorDevice -----------------------------------------------------------------------
    def _io_read(self, row: np.ndarray) -> int:
        s = self._state
        row[0:3] = s[0:3]
        row[3:7] = self._quat
        row[7:10] = s[3:6]
        row[10:13] = 0.0
        row[13:19] = np.nan
        row[19] = self._clock() * 1e-9
        # a VerseGrip's buttons (none without one); an Inverse3 has no gripper
        row[DS_BUTTONS] = self.buttons if self._grip_id is not None else np.nan
        row[DS_GRIPPER] = row[DS_GRIPPER_RATE] = np.nan
        return DEV_OK

    def _io_write(self, wrench: np.ndarray) -> int:
        f = self._f
        f[0], f[1], f[2] = float(wrench[0]), float(wrench[1]), float(wrench[2])
        if self._fault in (DEV_FAULT_LINK, DEV_FAULT_HARDWARE):
            # a lost device gets one zero force (if it still hears anything, it lets go), then is
            # not talked to until enable() finds it again: each try costs timeout_s
            if not self._zeroed:
                self._zeroed = True
                f[0] = f[1] = f[2] = 0.0
                self._exchange(f)
            return self._fault
        return self._exchange(f)

    _zeroed = False

    def _io_enable(self, on: bool) -> int:
        if not on:
            return DEV_OK
        self._zeroed = False
        if self.config.transport == "serial" and self._fault in (DEV_FAULT_LINK, DEV_FAULT_HARDWARE):
            self._dev.flush_input()
            ident = self._dev.device_wakeup_dict()
            if int(ident["device_id_ext"].int) == 0:
                return DEV_FAULT_LINK
        # one zero-force exchange: the device answers (and holds no force) before arming
        f = self._f
        f[0] = f[1] = f[2] = 0.0
        return self._exchange(f)

    def _io_close(self) -> None:
        if self.config.transport == "service":
            self._ws.close()


class _Websocket:
    """A blocking websocket client on ``websockets``' sans-I/O protocol: no background thread
    (its sync client keeps one reading, which holds a frame in flight at all times), one
    request and one reply per haptic step, the reply awaited at most ``timeout`` seconds."""

    def __init__(self, url: str, timeout_s: float) -> None:
        import socket

        from websockets.client import ClientProtocol
        from websockets.http11 import Response
        from websockets.uri import parse_uri

        uri = parse_uri(url)
        if uri.secure:
            raise DeviceUnavailable(f"device.url: {url}: the Inverse Service is local; use ws://")
        self._proto = ClientProtocol(uri, max_size=2 ** 20)
        self._sock = socket.create_connection((uri.host, uri.port), timeout=2.0)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._timeout = timeout_s
        self._texts: list[str] = []
        self._proto.send_request(self._proto.connect())
        self._flush()
        while True:
            ev = self._events(2.0)
            if isinstance(ev, Response):
                if ev.status_code != 101:
                    raise DeviceUnavailable(f"device.url: {url} refused the websocket (HTTP {ev.status_code})")
                break
        self._sock.settimeout(timeout_s)

    def _flush(self) -> None:
        for data in self._proto.data_to_send():
            if data:
                self._sock.sendall(data)

    def _events(self, timeout: float):
        """The next event (a handshake Response or a text message), waiting up to ``timeout``."""
        from websockets.frames import Opcode

        while True:
            response = None
            for ev in self._proto.events_received():  # all of them: a reply may share a read with the next
                if getattr(ev, "opcode", None) == Opcode.TEXT:
                    self._texts.append(ev.data.decode())
                elif getattr(ev, "opcode", None) is None:
                    response = ev
            self._flush()  # pongs, close frames
            if response is not None:
                return response
            if self._texts:
                return self._texts.pop(0)
            self._sock.settimeout(timeout)
            data = self._sock.recv(65536)
            if not data:
                raise ConnectionError("the Inverse Service closed the connection")
            self._proto.receive_data(data)

    def send(self, text: str) -> None:
        self._proto.send_text(text.encode())
        self._flush()

    def recv(self, timeout: float | None = None) -> str:
        import socket

        try:
            return self._events(self._timeout if timeout is None else timeout)
        except socket.timeout:
            raise TimeoutError("no frame from the Inverse Service") from None

    def close(self) -> None:
        try:
            self._proto.send_close()
            self._flush()
        except Exception:  # noqa: BLE001 - closing a broken connection
            pass
        self._sock.close()


def _as_int(v) -> int:
    try:
        return int(v, 16) if isinstance(v, str) else int(v)
    except (TypeError, ValueError):
        return -1


def make_haply_device(config: dict, *, period_s: float, clock_ns=None) -> HaplyDevice:
    """Entry point ``haply`` (see the module docstring)."""
    return HaplyDevice(config, period_s=period_s, clock_ns=clock_ns)


make_haply_device.effective_config = effective_config
make_haply_device.kinds = ("spatial",)

#: for `hapticproxy plugins` and `hapticproxy devices`
make_haply_device.about = {"clock": "loop", "package": "haplyhardwareapi", "module": "HaplyHardwareAPI", "models": ["Inverse3"], "transports": ["serial", "service"]}
