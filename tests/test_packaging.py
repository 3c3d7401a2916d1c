"""The namespaced distribution (issue #12): the card's top-level folders install as
sub-packages of ``stereodem`` and nothing generic lands at the top of site-packages."""
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"stereodem": "stereodem", "sensor": "stereodem.sensor", "stereo": "stereodem.stereo",
           "post": "stereodem.post", "ortho": "stereodem.ortho"}


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
    assert found == listed, (found - listed, listed - found)
    assert all(p == "stereodem" or p.startswith("stereodem.") for p in listed)


def test_generic_names_are_not_importable_from_the_distribution():
    import importlib.util
    import sys
    # the repository root is not on sys.path here only when tests run from an install; what
    # must hold everywhere is that the package's own modules import through the namespace
    import stereodem.sensor.models.base as base
    assert base.__name__ == "stereodem.sensor.models.base"
    for generic in ("sensor", "stereo", "post", "ortho"):
        spec = importlib.util.find_spec(generic)
        assert spec is None or Path(spec.origin).parent.parent == ROOT, (generic, spec)
    assert "sensor" not in sys.modules
