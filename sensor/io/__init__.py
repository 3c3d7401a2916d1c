"""Files in and out (rasters: :mod:`stereodem.core.raster`): RPC formats, ASTER product geometry,
model sidecars and ground control point tables."""
