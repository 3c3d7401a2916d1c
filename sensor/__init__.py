"""Sensor geometry, in rooms:

* :mod:`.geo` — rotations, space intersection (geodesy, grids, DEMs: :mod:`stereodem.core`);
* :mod:`.models` — the sensor models (frame, pushbroom, ASTER, RPC, fitted generic models,
  image-space corrections) on one contract;
* :mod:`.io` — file readers and writers (rasters, RPC formats, ASTER geometry, model sidecars,
  GCP tables);
* :mod:`.estimation` — RPC fitting, regularisation and adjustment;
* :mod:`.simulation` — the scene simulator.

Every model follows the contract of :class:`stereodem.sensor.models.base.SensorModel`:
``project(lon, lat, h) -> (col, row)`` and ``localize(col, row, h) -> (lon, lat)``.
"""
