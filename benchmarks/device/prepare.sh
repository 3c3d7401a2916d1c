#!/usr/bin/env bash
# Prepare, on this machine, the scaling measurement on the `device` tool's machine (16 cores,
# Python 3.12, no network; issue #28's 16-core figures). Run from anywhere:
#
#     bash benchmarks/device/prepare.sh
#
# It downloads the Python 3.12 wheels of the packages that machine lacks (its image holds
# numpy, scipy, opencv-python-headless, matplotlib, psutil, threadpoolctl, tqdm, click, attrs,
# certifi, pyparsing: /work/.library/device/KINDS.md) into .whl/ at the repository root and
# keeps that folder out of git. The working tree plus .whl/ must stay under the tool's 64 MiB.
# Then one device call runs benchmarks/device/run_scaling.sh (see its header).
set -euo pipefail
cd "$(dirname "$0")/../.."
mkdir -p .git/info
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >>.git/info/exclude
rm -rf .whl && mkdir .whl
# the versions CI tests with (rasterio 1.5 is 39 MB: it would not fit beside the tree)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    "rasterio==1.4.4" "pyproj==3.7.2" "pyhdf==0.11.7" "affine==3.0.1" "cligj==0.7.2" \
    "click-plugins==1.1.1.2" "shapely==2.2.0"
mib() { awk '{s += $1} END {printf "%.1f", s / 1048576}'; }
tree=$(git ls-files -z | xargs -0 stat -c %s | mib)
whl=$(stat -c %s .whl/*.whl | mib)
echo "wheels ${whl} MiB + tracked tree ${tree} MiB (the device tool takes 64 MiB in all)"
