"""Dependencies point one way (issue #23): core <- sensor <- stereo, post, ortho <- the
application. Every import statement of a library package, module-level or inside a function,
is checked by reading the source (no import side effects)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = {
    "core": "core",
    "sensor": "sensor",
    "stereo": "stereo",
    "post": "post",
    "ortho": "ortho",
    "app": "src/stereodem",
}
# what each package may import from stereodem (besides itself)
ALLOWED = {
    "core": set(),
    "sensor": {"core"},
    "stereo": {"core", "sensor"},
    "post": {"core", "sensor"},
    "ortho": {"core", "sensor"},
}
PACKAGE_OF = {
    "core": "core",
    "sensor": "sensor",
    "stereo": "stereo",
    "post": "post",
    "ortho": "ortho",
}


def _imported_packages(path: Path):
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] != "stereodem":
                continue
            yield node.lineno, PACKAGE_OF.get(parts[1], "app") if len(parts) > 1 else "app"


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_library_packages_import_only_downwards(package):
    bad = []
    for path in sorted((ROOT / FOLDERS[package]).rglob("*.py")):
        for line, used in _imported_packages(path):
            if used != package and used not in ALLOWED[package]:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports stereodem.{used}")
    assert not bad, "\n".join(bad)
