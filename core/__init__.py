"""The project's core, below every other package (issue #23): what sensor models, stereo,
post-processing, orthoimages and the application all stand on.

* :mod:`.errors` — the exception hierarchy (``StereodemError``, ``InputError``, ...);
* :mod:`.geodesy` — WGS84, ECEF/ENU, UTM, EGM96 (pyproj);
* :mod:`.grid` — ``MapGrid``, the one map-grid type;
* :mod:`.dem` — ``DEM``, the one DEM type (heights + vertical reference + companion layers);
* :mod:`.raster` — GeoTIFF/COG reading and atomic writing, output checks;
* :mod:`.memory` — will an allocation fit (checked before it); the allocator keeping freed memory;
* :mod:`.morphology` — square dilations of boolean masks (OpenCV).

Nothing here imports another stereodem package.
"""
