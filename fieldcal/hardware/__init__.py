"""Devices: :class:`Stage`/:class:`Camera` protocols, simulated devices, the PI GCS2 client and its emulator,
optional backends (pipython, pypylon) and the plug-in registry. See docs/hardware.md."""

from .protocols import Camera, DeviceFault, Frame, Stage
from .registry import make_device, parse_device_string

__all__ = ["Stage", "Camera", "Frame", "DeviceFault", "make_device", "parse_device_string"]
