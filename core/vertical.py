"""Vertical references of heights: the names every package, the command line, the
configuration checks and the docs take their choices from (a light module: the CLI's
parsers import it)."""

from typing import Literal, get_args

GEOID, ELLIPSOID = "geoid", "ellipsoid"

#: EGM96 geoid heights or WGS84 ellipsoidal heights
Vertical = Literal["geoid", "ellipsoid"]
VERTICALS: tuple[str, ...] = get_args(Vertical)
