"""Print pip constraints that pin every declared lower bound of pyproject.toml (the runtime
dependencies and the ``test`` extra) to that version: ``numpy>=1.24`` -> ``numpy==1.24.*``,
``rasterio>=1.3.8`` -> ``rasterio==1.3.8``. ``.ci/run`` installs the project with them in a
second environment and runs the fast subset there, so that the ``>=`` bounds stay true.

Usage: ``python .ci/minimum_constraints.py > constraints.txt`` (Python >= 3.11: tomllib).
"""

import re
import sys
from pathlib import Path

import tomllib


def constraints(pyproject: Path) -> list[str]:
    project = tomllib.loads(pyproject.read_text())["project"]
    out = []
    for req in project["dependencies"] + project["optional-dependencies"]["test"]:
        m = re.fullmatch(r"\s*([A-Za-z0-9_.-]+)(\[[^\]]*\])?\s*>=\s*([0-9.]+)\s*", req)
        if not m:
            sys.exit(f"{pyproject}: cannot read a lower bound from {req!r}")
        name, version = m.group(1), m.group(3)
        pin = f"=={version}" if version.count(".") >= 2 else f"=={version}.*"
        out.append(f"{name}{pin}")
        if name == "dask" and "distributed" in (m.group(2) or ""):
            out.append(f"distributed{pin}")  # the extra pins the same release
    return out


if __name__ == "__main__":
    root = Path(__file__).resolve().parents[1]
    print("\n".join(constraints(root / "pyproject.toml")))
