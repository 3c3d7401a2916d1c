"""Sensor geometry: geodesy, DEM access, sensor models (frame, pushbroom, ASTER, RPC, fitted
generic models), adjustment and scene simulation.

Every model follows the contract of :class:`sensor.model.SensorModel`:
``project(lon, lat, h) -> (col, row)`` and ``localize(col, row, h) -> (lon, lat)``.
"""
from .errors import StereodemError  # noqa: F401
