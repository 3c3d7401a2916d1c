#!/usr/bin/env bash
# On the `device` tool's machine (16 cores, Python 3.12, no network), after
# benchmarks/device/prepare.sh here. One call, e.g.
#
#     run(command="bash benchmarks/device/run_scaling.sh", carry=[".whl"], timeout_s=540)
#
# installs the carried wheels and stereodem into /tmp/site, simulates the full-size ASTER
# granule (about 40 s on 2 cores), runs benchmarks/bench_scaling.py (default: --workers 2 4 8
# 16 --repeat 2; SCALING_ARGS replaces that) and leaves its JSON and log in $OUT, the files
# that come back. A round took 143 s on 16 cores in the table (older code), so two
# rounds fit in one call. Record which machine gave the figures (machine.txt, the JSON).
set -uo pipefail
OUT=${OUT:-/tmp/device_out}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
SITE=${SITE:-/tmp/site}
$PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$SITE" .whl/*.whl || exit 1
# stereodem itself, from this tree (setuptools is there; nothing is fetched)
$PY -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --upgrade \
    --target "$SITE" . || exit 1
export PYTHONPATH="$SITE" PYTHONUNBUFFERED=1
{
    echo "machine: $(nproc) cores; $(grep -m1 'model name' /proc/cpuinfo)"
    free -g | head -2
    $PY -c "import sys, numpy, scipy, cv2, rasterio, pyproj, matplotlib
print(sys.version.split()[0], 'numpy', numpy.__version__, 'scipy', scipy.__version__,
      'opencv', cv2.__version__, 'rasterio', rasterio.__version__,
      'GDAL', rasterio.__gdal_version__, 'pyproj', pyproj.__version__)"
} 2>&1 | tee "$OUT/machine.txt"
# SCALING_ARGS last: its options override these (argparse keeps the last)
# shellcheck disable=SC2086
$PY benchmarks/bench_scaling.py --out /tmp/bench_scaling \
    --results "$OUT/bench_scaling_device.json" ${SCALING_ARGS:---workers 2 4 8 16 --repeat 2} \
    2>&1 | tee "$OUT/bench_scaling_device.log"
