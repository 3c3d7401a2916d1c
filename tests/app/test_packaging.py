"""The namespaced distribution (issue #12): the card's top-level folders install as
sub-packages of ``stereodem`` and nothing generic lands at the top of site-packages.
The application sits in ``src/stereodem`` (issue #23) so that no root-level ``stereodem/``
folder shadows a non-editable install when tests run from the repository root."""

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = {
    "src/stereodem": "stereodem",
    "core": "stereodem.core",
    "sensor": "stereodem.sensor",
    "stereo": "stereodem.stereo",
    "post": "stereodem.post",
    "ortho": "stereodem.ortho",
}


def _config():
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_folder_is_installed_under_the_namespace():
    cfg = _config()
    listed = set(cfg["packages"])
    assert cfg["package-dir"] == {v: k for k, v in FOLDERS.items()}
    found = set()
    for folder, name in FOLDERS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            found.add(".".join([name, *rel.parts]))
        # the data folders: namespace packages of package data (no code, no __pycache__)
        for data in (ROOT / folder).rglob("data"):
            for d in [data, *data.rglob("*")]:
                if d.is_dir() and d.name != "__pycache__" and any(f.is_file() for f in d.iterdir()):
                    found.add(".".join([name, *d.relative_to(ROOT / folder).parts]))
    assert found == listed, (found - listed, listed - found)
    data_packages = {p for p in listed if ".data" in p}
    assert data_packages and data_packages <= set(cfg["package-data"]), data_packages
    assert all(p == "stereodem" or p.startswith("stereodem.") for p in listed)


def test_generic_names_are_not_importable_from_the_distribution():
    # the repository root is not on sys.path here only when tests run from an install; what
    # must hold everywhere is that the package's own modules import through the namespace
    import stereodem.sensor.models.base as base

    assert base.__name__ == "stereodem.sensor.models.base"
    for generic in ("core", "sensor", "stereo", "post", "ortho"):
        spec = importlib.util.find_spec(generic)
        assert spec is None or Path(spec.origin).parent.parent == ROOT, (generic, spec)
    assert "sensor" not in sys.modules


def test_ci_installs_what_the_readme_says():
    """The README's test command and .ci/run install the same things (a step only CI takes
    would make the README's command skip or fail tests on a fresh machine; CI installs without
    the README's -e, test_no_root_level_folder_shadows_the_installed_package), and the
    minimum-version environment pins every declared lower bound."""
    readme = (ROOT / "README.md").read_text()
    line = next(ln for ln in readme.splitlines() if 'pip install -e ".[test]"' in ln)
    install = re.match(r"\s*(.*?)\s*&& python -m pytest -q", line).group(1)
    ci = (ROOT / ".ci" / "run").read_text()
    ci_install = install.replace("pip install -e ", "pip install ")
    assert f"TEST_INSTALL='{ci_install}'" in ci
    others = re.sub(r'pip install -q "ruff[=<>0-9.]*".*', "", ci.replace(ci_install, ""))
    assert ci.count('eval "$TEST_INSTALL"') == 2
    assert not [
        ln for ln in others.splitlines() if "pip install" in ln and "--upgrade pip" not in ln
    ]
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pins = subprocess.run(
        [sys.executable, str(ROOT / ".ci" / "minimum_constraints.py")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    bounds = project["dependencies"] + project["optional-dependencies"]["test"]
    assert len([p for p in pins if not p.startswith("distributed")]) == len(bounds)
    for req in bounds:
        name, version = re.fullmatch(r"([A-Za-z0-9_.-]+)(?:\[.*\])?>=([0-9.]+)", req).groups()
        assert any(p.startswith(f"{name}=={version}") for p in pins), (req, pins)


def test_no_root_level_folder_shadows_the_installed_package():
    """`pip install .` then `python -m pytest` in the clone: the clone's root is sys.path[0], so
    a folder named like the package there would be imported instead of the installed one and
    miss the mapped sub-packages (ModuleNotFoundError: stereodem.sensor)."""
    # the imports are what this test checks (here, not at the top: a failure is this test's)
    import stereodem
    import stereodem.sensor

    assert not (ROOT / "stereodem").exists()
    assert not (ROOT / "stereodem.py").exists()
    assert Path(stereodem.__file__).parent != ROOT / "stereodem"
    assert stereodem.sensor.__name__ == "stereodem.sensor"
