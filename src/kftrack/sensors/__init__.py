"""Sensor models and sensor data: one module per sensor family.

- :mod:`kftrack.sensors.radar` -- radar measurements: 2-D range-bearing, 3-D range-azimuth-elevation.
- :mod:`kftrack.sensors.lidar` -- a floor plan of walls and a simulated 2-D LIDAR (ray casting).
- :mod:`kftrack.sensors.gps` -- NMEA 0183 sentences and logs, and the geodesy from fixes to metres.
- :mod:`kftrack.sensors.ardrone` -- the Parrot AR.Drone's sensors: units, altimeter format, statistics, logs.

Each module is imported on first use (``kftrack.sensors.radar`` after ``import kftrack``; PEP 562).
"""
from __future__ import annotations

import importlib

_MODULES = ("radar", "lidar", "gps", "ardrone")

__all__ = sorted(_MODULES)


def __getattr__(name: str):
    """``kftrack.sensors.<module>``: import the module on first use (PEP 562)."""
    if name in _MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
