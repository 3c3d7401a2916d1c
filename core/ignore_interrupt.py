"""Imported first by the tile pool's fork server (``stereo.fork_server._PRELOAD``): this
process ignores SIGINT from then on.

A Ctrl-C reaches the whole process group. CPython's fork server sets SIGINT to ``SIG_IGN``
only after it has imported its preload modules (about 1 s of numpy, SciPy, OpenCV, rasterio
and the tile code), so a Ctrl-C in a job's first second or so interrupted those imports and
printed the server's 30-line ``KeyboardInterrupt`` traceback above the command's own one-line
message. Imported first, this module leaves only the interpreter's start (tens of
milliseconds) to such a stop. The command's own process handles the stop; the server and the
workers it forks end with it (their workers ignore SIGINT too: ``stereo.runner``).
"""

import signal

signal.signal(signal.SIGINT, signal.SIG_IGN)
