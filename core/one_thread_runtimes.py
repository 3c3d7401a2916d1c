"""Imported by the tile pool's fork server before the tile code (``stereo.fork_server._PRELOAD``):
the BLAS and OpenMP runtimes that the server's next imports load start with one thread.

OpenBLAS starts a thread per core when it is loaded (NumPy's, SciPy's and OpenCV's each), and
those threads spin for a while before they sleep: the server's imports (numpy, SciPy, OpenCV,
rasterio, the tile code) took 0.85 CPU s for 0.56 s on 2 cores, 0.48 CPU s for 0.48 s with one
BLAS thread (``OPENBLAS_NUM_THREADS=1``, three runs each), CPU spent at every pool's start on
threads the server never uses (in ``stereodem run`` at 2 workers on the full ASTER granule the
stereo stage's worker CPU beyond its tiles' own fell from 1.39-1.48 to 1.24-1.35 s, three
alternating pairs: the imports overlap the command's own start there). Its workers inherit
these settings and pin their own budget at their start
(:func:`stereodem.core.threads.pin_threads`, which raises a runtime's threads where a worker
has more than one core), so the tiles run on the threads they did before (the full granule's
rasters bit-identical).

The command's own process is not affected: this module is imported in the server only.
"""

import os

from stereodem.core.threads import ENV_VARS

for _var in ENV_VARS:
    os.environ[_var] = "1"
