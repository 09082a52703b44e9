"""kftrack: the package behind the course-book *Kalman filtering for tracking*.

Layers, lowest first: numerics (:mod:`kftrack.kalman`, :mod:`kftrack.engines`, :mod:`kftrack.metrics`,
:mod:`kftrack.tuning`), models,
worlds (:mod:`kftrack.datasets`, :mod:`kftrack.adsb`), presentation (:mod:`kftrack.plotting`).
"""
__version__ = "0.1.0"
