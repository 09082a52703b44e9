"""Test configuration: headless matplotlib for pytest-side plotting tests.

The Agg backend is set here, not through MPLBACKEND in the environment, so notebook
kernels started by nbval keep the inline backend and their figures.
"""
import matplotlib

matplotlib.use("Agg")
