"""Haptic device drivers: the interface (``base``), simulated devices, the remote-device link."""
from .base import (  # noqa: F401
    DEV_NSTATE, DS_HAND, DS_POSE, DS_TIME, DS_TWIST, DeviceDriver, DeviceLimits, load_device,
)
