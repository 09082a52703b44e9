"""Sensor models and sensor data: one module per sensor family.

- :mod:`kftrack.sensors.radar` -- radar measurements: 2-D range-bearing, 3-D range-azimuth-elevation.
- :mod:`kftrack.sensors.lidar` -- a floor plan of walls and a simulated 2-D LIDAR (ray casting).
- :mod:`kftrack.sensors.gps` -- NMEA 0183 sentences and logs, and the geodesy from fixes to metres.
- :mod:`kftrack.sensors.ardrone` -- the Parrot AR.Drone's sensors: units, altimeter format, statistics, logs.
- :mod:`kftrack.sensors.surveillance` -- a simulated rotating surveillance radar over recorded traffic: scans of plots.

Each module is imported on first use (``kftrack.sensors.radar`` after ``import kftrack``; PEP 562).
"""
from __future__ import annotations

from .. import lazy_modules

_MODULES = ("radar", "lidar", "gps", "ardrone", "surveillance")

__all__ = sorted(_MODULES)


__getattr__, __dir__ = lazy_modules(__name__, _MODULES, globals())  # kftrack.sensors.<module> on first use
