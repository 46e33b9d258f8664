"""Haptic device drivers: the interface (``base``: ``DeviceDriver``, ``DeviceInfo``, ``DeviceLimits``),
simulated devices (``sim``), the remote-device link (``remote``) and the vendor drivers on their
vendors' Python packages (``forcedimension``, ``haply``, ``touch``; shared logic in ``vendor``, the
models' figures in ``models``, what is connected in ``detect``)."""
from .base import (  # noqa: F401
    DEV_NSTATE, DS_HAND, DS_POSE, DS_TIME, DS_TWIST, DeviceDriver, DeviceLimits, load_device,
)
