"""Test configuration: headless matplotlib for pytest-side plotting tests; no time limits.

The Agg backend is set here, not through MPLBACKEND in the environment, so notebook
kernels started by nbval keep the inline backend and their figures. Hypothesis runs
without its per-example deadline everywhere: a test checks values, never speed, and on a
loaded 2-core machine an example that takes 0.7 ms took 290 ms once (a flaky failure).
"""
import matplotlib
from hypothesis import settings

matplotlib.use("Agg")
settings.register_profile("kftrack", deadline=None)
settings.load_profile("kftrack")
