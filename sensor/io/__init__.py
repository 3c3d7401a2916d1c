"""Files in and out: rasters (GeoTIFF), RPC formats, ASTER product geometry, model sidecars
and ground control point tables."""
