"""The Earth side of the geometry: WGS84 geodesy and EGM96 (pyproj), attitude rotations, and
DEM access with its vertical reference."""
