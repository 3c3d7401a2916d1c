"""Docs that stay true (issue #19): docs/configuration.md is what the generator makes of the
configuration dataclasses, and the Python API example in docs/api.md runs."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest
from helpers.strict_json import strict_loads

from stereodem.config import SECTIONS
from stereodem.docgen import _attributes_section, configuration_markdown, main, section_table

ROOT = Path(__file__).resolve().parents[2]


def test_committed_configuration_md_is_the_generators_output():
    committed = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert committed == configuration_markdown(), (
        "docs/configuration.md is stale: python -m stereodem.docgen > docs/configuration.md"
    )
    assert main(["--check", str(ROOT / "docs" / "configuration.md")]) == 0


def test_every_config_section_and_key_is_documented():
    text = configuration_markdown()
    for name, cls in SECTIONS.items():
        assert f"## `[{name}]`" in text
        section = text.split(f"## `[{name}]`", 1)[1].split("\n## ", 1)[0]
        for g in dataclasses.fields(cls):
            if g.init:
                assert f"| `{g.name}` |" in section, (name, g.name)


@dataclasses.dataclass
class _Toy:
    """Toy settings.

    Attributes
    ----------
    alpha, beta : float
        Two weights (m), shared text.
    mode : {"fast", "exact"}
    """

    alpha: float = 1.5
    beta: float = 2.0
    mode: str = "fast"
    size: tuple = (3, 4)  # cells per side
    name: str | None = None


def test_generator_reads_types_defaults_docstring_and_comments():
    docs = _attributes_section(_Toy.__doc__)
    assert docs["alpha"] == docs["beta"] == ("float", "Two weights (m), shared text.")
    assert docs["mode"] == ('{"fast", "exact"}', "")
    rows = section_table(_Toy).splitlines()[2:]
    assert rows[0] == "| `alpha` | float | `1.5` | Two weights (m), shared text. |"
    assert rows[2] == '| `mode` | {"fast", "exact"} | `"fast"` |  |'
    assert rows[3] == "| `size` | `tuple` | `[3, 4]` | cells per side |"
    assert rows[4] == "| `name` | `str \\| None` | `none` |  |"


def _api_example() -> str:
    text = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 1
    return blocks[0]


@pytest.mark.slow
def test_api_example_runs(capsys):
    ns = {"__name__": "__docs_api__"}
    exec(compile(_api_example(), str(ROOT / "docs" / "api.md"), "exec"), ns)
    out = ns["out"]
    for name in ("dem.tif", "ortho_left.tif", "raw/count.tif", "assess/report.html"):
        assert (out / name).exists(), name
    s = ns["s"]
    assert np.isfinite(s["nmad"]) and 0 < s["nmad"] < 10
    printed = capsys.readouterr().out
    assert f"NMAD {s['nmad']:.2f} m" in printed


def test_readme_figures_summarises_every_committed_result():
    spec = importlib.util.spec_from_file_location(
        "readme_figures", ROOT / "benchmarks" / "readme_figures.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    text = mod.figures_markdown()
    results = sorted((ROOT / "benchmarks" / "results").glob("*.json"))
    bullets = [ln for ln in text.splitlines() if ln.startswith("* ")]
    assert len(bullets) == len(results)
    assert "summary unavailable" not in text

    demo = json.loads((ROOT / "benchmarks" / "results" / "bench_demo.json").read_text())
    assert f"NMAD {demo['default_seed_figures']['nmad_m']:.2f} m" in text


def test_benchmark_results_are_strict_json():
    """Every committed result file is what jq and JavaScript read (no NaN or Infinity: the
    benchmarks write through ``stereodem.core.jsonutil.dumps``)."""
    for path in sorted((ROOT / "benchmarks" / "results").glob("*.json")):
        try:
            strict_loads(path.read_text())
        except ValueError as exc:
            raise AssertionError(f"{path.name}: {exc}") from None


def test_readmes_carry_the_figures_the_results_give():
    """README.md's list of measured figures and benchmarks/README.md's table are exactly what
    ``benchmarks/readme_figures.py --write`` makes from the committed result files (a rerun
    that is not regenerated, or a figure edited by hand, fails here)."""
    spec = importlib.util.spec_from_file_location(
        "readme_figures", ROOT / "benchmarks" / "readme_figures.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    readme = (ROOT / "README.md").read_text()
    assert mod.figures_markdown() + mod.LIST_END in readme
    bench = (ROOT / "benchmarks" / "README.md").read_text()
    assert mod.TABLE_START + "\n" + mod.benchmarks_table() + mod.TABLE_END in bench
