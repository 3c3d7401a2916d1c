"""Sensor models, all on one contract (:class:`stereodem.sensor.models.base.SensorModel`):
``project(lon, lat, h) -> (col, row)`` and ``localize(col, row, h) -> (lon, lat)``.

frame camera (:mod:`.frame`), pushbroom with ephemeris and attitude (:mod:`.pushbroom`,
:mod:`.ephemeris`), ASTER from its product geometry (:mod:`.aster`), RPC00B (:mod:`.rpc`), the
GCP-fitted generic models of the Ok thesis (:mod:`.generic`), the parametric orbital models of
Topan's survey (:mod:`.orbital`: Topan's EOP-polynomial line of sight, Orun & Natarajan,
Toutin-type, Kratky) and image-space corrections of any model (:mod:`.corrected`). Adjustable
parameters are named vectors (:mod:`.parameters`).
"""
