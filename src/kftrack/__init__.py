"""kftrack: the package behind the course-book *Kalman filtering for tracking*.

Layers, lowest first: numerics (:mod:`kftrack.kalman`, :mod:`kftrack.metrics`), models,
worlds (:mod:`kftrack.datasets`), presentation (:mod:`kftrack.plotting`).
"""
__version__ = "0.1.0"
