"""What is connected: ``hapticproxy devices`` (one row per device found, one per vendor driver
that is installed but finds nothing or cannot look).

Each vendor's own way of listing, through its package: Force Dimension ``dhdGetDeviceCount`` and
``dhdOpenID`` / system name / serial for each (the device is closed again at once); Haply
``detect_inverse3s()`` (serial ports by USB vendor id) plus the Inverse Service's inventory when
it answers at its default address; 3D Systems ``hdInitDevice`` for each configured device name
(``Default Device`` unless others are named). Opening a device another program holds fails:
that device is listed as busy, never taken from that program.
"""
from __future__ import annotations

import importlib.util


def _row(driver: str, status: str, **kw) -> dict:
    return {"driver": driver, "status": status, **kw}


def forcedimension() -> list[dict]:
    if importlib.util.find_spec("forcedimension_core") is None:
        return [_row("forcedimension", "not installed", fix="pip install 'hapticproxy[devices]'")]
    from .forcedimension import sdk
    from .vendor import DeviceUnavailable

    try:
        fdc = sdk()
    except DeviceUnavailable as exc:
        return [_row("forcedimension", "unusable", why=str(exc).removeprefix("device.driver: forcedimension: "))]
    dhd = fdc.dhd
    n = int(dhd.getDeviceCount())
    if n <= 0:
        return [_row("forcedimension", "installed, nothing connected")]
    out = []
    for i in range(n):
        dev = dhd.openID(i)
        if dev < 0:
            out.append(_row("forcedimension", "busy", index=i, why=dhd.errorGetLastStr()))
            continue
        try:
            out.append(_row("forcedimension", "connected", model=dhd.getSystemName(dev) or "?",
                            serial=str(dhd.getSerialNumber(dev)), index=i,
                            config=f'driver = "forcedimension", kind = "spatial", serial = {dhd.getSerialNumber(dev)}'))
        finally:
            dhd.close(dev)
    return out


def haply(service_url: str = "ws://127.0.0.1:10001") -> list[dict]:
    out = []
    if importlib.util.find_spec("HaplyHardwareAPI") is None:
        out.append(_row("haply", "not installed", fix="pip install 'hapticproxy[devices]'"))
    else:
        import HaplyHardwareAPI as H  # noqa: N814

        for port in H.detect_inverse3s():
            out.append(_row("haply", "connected", model="Inverse3", port=port,
                            config=f'driver = "haply", kind = "spatial", port = "{port}"'))
    if importlib.util.find_spec("websockets") is not None:
        from .haply import _Websocket
        import json

        try:
            ws = _Websocket(service_url, 0.3)
            try:
                inv = json.loads(ws.recv(0.3))
            finally:
                ws.close()
            for d in inv.get("inverse3") or []:
                out.append(_row("haply", "connected", model="Inverse3", serial=str(d.get("device_id")),
                                via=service_url, config=f'driver = "haply", kind = "spatial", transport = "service", '
                                                        f'url = "{service_url}"'))
        except Exception:  # noqa: BLE001 - no service running: nothing to list
            pass
    if not any(r["status"] == "connected" for r in out) and not any(r["status"] == "not installed" for r in out):
        out.append(_row("haply", "installed, nothing connected"))
    return out


def touch(names=("Default Device",)) -> list[dict]:
    if importlib.util.find_spec("pyOpenHaptics") is None:
        return [_row("touch", "not installed", fix="pip install 'hapticproxy[devices]'")]
    from .touch import HD_DEVICE_MODEL_TYPE, HD_DEVICE_SERIAL_NUMBER, HD_INVALID_HANDLE, _proto, hd
    from .vendor import DeviceUnavailable

    try:
        lib = hd()._lib_hd
    except DeviceUnavailable as exc:
        return [_row("touch", "unusable", why=str(exc).removeprefix("device.driver: touch: "))]
    _proto(lib)
    out = []
    for name in names:
        h = int(lib.hdInitDevice(name.encode()))
        if h == HD_INVALID_HANDLE:
            lib.hdGetError()
            continue
        try:
            lib.hdMakeCurrentDevice(h)
            out.append(_row("touch", "connected", model=(lib.hdGetString(HD_DEVICE_MODEL_TYPE) or b"").decode(),
                            serial=(lib.hdGetString(HD_DEVICE_SERIAL_NUMBER) or b"").decode(), name=name,
                            config=f'driver = "touch", kind = "spatial", device_name = "{name}"'))
        finally:
            lib.hdDisableDevice(h)
    return out or [_row("touch", "installed, nothing connected", names=list(names))]


def detect(*, touch_names=("Default Device",), service_url: str = "ws://127.0.0.1:10001") -> list[dict]:
    return forcedimension() + haply(service_url) + touch(touch_names)
