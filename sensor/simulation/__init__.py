"""Scene simulation: stereo pairs rendered through the project's own sensor models over a real
DEM and texture, with known truth."""
