"""The Earth side of the sensor geometry: attitude rotations and space intersection (two rays
to a ground point). Geodesy, map grids and DEMs are in :mod:`stereodem.core`."""
