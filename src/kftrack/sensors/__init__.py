"""Sensor models and sensor data: one module per sensor family."""
