"""The allocator setting of the processes that run tiles and jobs
(:func:`stereodem.core.memory.keep_freed_memory`)."""

import platform
import subprocess
import sys
import textwrap

import pytest

glibc_only = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")

#: a stage's memory pattern: ~100 MB of arrays alive at once, then all freed, twice; prints
#: the page faults of the second pass (the first may fault: the pages are new to the process)
_PATTERN = """
import resource
import numpy as np

def one_pass():
    live = [np.ones(s * 2**20 // 8) for s in (20, 12, 24, 8, 16, 20)]
    return sum(float(a[0]) for a in live)

def faults_of_a_second_pass():
    one_pass()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    one_pass()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
    return 0
"""


def _faults(then):
    code = textwrap.dedent(_PATTERN) + textwrap.dedent(then)
    p = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    return int(p.stdout.split()[-1])


@pytest.mark.slow  # two subprocesses
@glibc_only
def test_tiles_run_in_this_process_keep_the_memory_they_free():
    """With one worker the tiles run in the calling process, which is then set like a pool
    worker, so a tile that frees and allocates again reuses its pages; a plain interpreter
    faults the pattern in afresh (measured here, as the reference)."""
    plain = _faults("faults_of_a_second_pass()\n")
    if plain < 200:  # e.g. transparent huge pages for everything: 2 MB per fault
        pytest.skip(f"{plain} page faults per pass without it: too few to compare")
    in_process = _faults(
        """
        from stereodem.stereo.runner import run_tiles
        from stereodem.stereo.tiling import tile_grid
        run_tiles(lambda tile, ctx: faults_of_a_second_pass(), tile_grid(8, 8, 8), {}, workers=1)
        """
    )
    assert in_process < plain / 10, (in_process, plain)
