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


def test_committed_cli_md_is_the_generators_output():
    from stereodem import clidoc

    committed = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert committed == clidoc.cli_markdown(), (
        "docs/cli.md is stale: python -m stereodem.clidoc > docs/cli.md"
    )
    assert clidoc.main(["--check", str(ROOT / "docs" / "cli.md")]) == 0


def test_every_command_and_option_is_in_the_cli_reference(tmp_path):
    """Each sub-command's section lists every option and argument its parser has (help
    aside), with its required mark and the default its help text does not state."""
    import argparse

    from stereodem import clidoc
    from stereodem.commands import COMMANDS

    text = clidoc.cli_markdown()
    subs = clidoc._subparsers()
    assert list(subs) == list(COMMANDS)
    for name, p in subs.items():
        section = text.split(f"## `stereodem {name}`\n", 1)[1].split("\n## ", 1)[0]
        for a in p._actions:
            if isinstance(a, argparse._HelpAction) or a.help == argparse.SUPPRESS:
                continue
            rows = [r for r in section.splitlines() if r.startswith("| `")]
            if a.option_strings:  # the row whose first cell names the option
                row = next(
                    (r for r in rows if f"`{a.option_strings[0]}`" in r.split(" | ")[0]), None
                )
            else:  # a positional: its row has no option and says its help
                row = next((r for r in rows if " ".join(a.help.split())[:30] in r), None)
            assert row is not None, (name, a.dest)
            assert a.help, f"stereodem {name} {a.option_strings or a.dest}: no help text"
            for s in a.option_strings:
                assert f"`{s}`" in row, (name, s)
            if a.required and a.option_strings:
                assert "*required*" in row, (name, a.dest)
    # a default the help does not state is added: ortho --resampling says none of its own
    ortho = text.split("## `stereodem ortho`", 1)[1].split("\n## ", 1)[0]
    assert "(default: bilinear)" in ortho
    # a stale file is reported
    stale = tmp_path / "cli.md"
    stale.write_text(text.replace("stereodem ortho", "stereodem orto", 1), encoding="utf-8")
    assert clidoc.main(["--check", str(stale)]) == 1
    # --check without its path is a usage error, not a traceback
    assert clidoc.main(["--check"]) == 2


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
    """README.md's list of measured figures and table of issue 28's targets, and
    benchmarks/README.md's table, are exactly what
    ``benchmarks/readme_figures.py --write`` makes from the committed result files (a rerun
    that is not regenerated, or a figure edited by hand, fails here)."""
    spec = importlib.util.spec_from_file_location(
        "readme_figures", ROOT / "benchmarks" / "readme_figures.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    readme = (ROOT / "README.md").read_text()
    assert mod.figures_markdown() + mod.LIST_END in readme
    assert mod.TARGETS_START + "\n" + mod.scaling_targets() + mod.TARGETS_END in readme
    bench = (ROOT / "benchmarks" / "README.md").read_text()
    assert mod.TABLE_START + "\n" + mod.benchmarks_table() + mod.TABLE_END in bench


#: signatures docs/api.md writes out (as ``NAME(...)`` in backticks) -> what they describe
def _api_signatures():
    from stereodem import (
        DEM,
        ICP,
        AlongTrack,
        Coreg,
        CrossTrack,
        Curvature,
        DEMProducts,
        Deramp,
        NuthKaab,
        Ortho,
        VerticalShift,
        assess_dem,
        make_dem,
        orthorectify,
        parse_chain,
        read_points,
        write_geotiff,
        write_report,
    )
    from stereodem.ortho.drm import dem_gaps

    return {
        "Coreg.fit": Coreg.fit,
        "Coreg.apply": Coreg.apply,
        "NuthKaab": NuthKaab,
        "VerticalShift": VerticalShift,
        "Deramp": Deramp,
        "AlongTrack": AlongTrack,
        "CrossTrack": CrossTrack,
        "Curvature": Curvature,
        "ICP": ICP,
        "parse_chain": parse_chain,
        "read_points": read_points,
        "make_dem": make_dem,
        "orthorectify": orthorectify,
        "dem_gaps": dem_gaps,
        "DEM": DEM,
        "DEM.from_file": DEM.from_file,
        "DEM.reproject": DEM.reproject,
        "sample": DEM.sample,
        "write_geotiff": write_geotiff,
        "assess.assess_dem": assess_dem,
        "report.write_report": write_report,
        "write": (Ortho.write, DEM.write, DEMProducts.write),
    }


def _documented_signatures(text):
    """``(name, parameter list)`` of every ``NAME(params)`` in backticks whose name is a key of
    :func:`_api_signatures` (line breaks inside the backticks allowed)."""
    names = "|".join(re.escape(n) for n in sorted(_api_signatures(), key=len, reverse=True))
    for m in re.finditer(rf"`({names})\(([^`]*?)\)(?: -> [^`]*)?`", text, re.S):
        yield m.group(1), " ".join(m.group(2).split())


def _check_signature(doc_params: str, func) -> str | None:
    """Why a call written as the docs write ``doc_params`` does not fit ``func`` (None: fits).
    ``...`` stands for parameters left out; a parameter the docs show positional must be
    positional, one they show keyword-only may be either; literal defaults must agree."""
    import ast
    import inspect

    params = [p.strip() for p in doc_params.split(",") if p.strip()]
    call = bool(params) and params[0] == "..."  # ``f(..., key=value)``: a call's keywords
    if call:
        params[0] = "*"
    params = [p for p in params if p != "..."]
    tree = ast.parse(f"def f({', '.join(params)}): pass").body[0].args
    actual = inspect.signature(func).parameters
    positional = [
        n
        for n, p in actual.items()
        if p.kind is p.POSITIONAL_OR_KEYWORD and n not in ("self", "cls")
    ]
    doc_pos = [a.arg for a in tree.args]
    if doc_pos != positional[: len(doc_pos)]:
        return f"positional {doc_pos}, the code's {positional}"
    defaults = dict(zip(doc_pos[len(doc_pos) - len(tree.defaults) :], tree.defaults))
    for a, d in zip(tree.kwonlyargs, tree.kw_defaults):
        if a.arg not in actual:
            return f"no parameter {a.arg!r}"
        defaults[a.arg] = d
    for name, node in defaults.items():
        if node is None or call:
            continue
        try:
            value = ast.literal_eval(node)
        except ValueError:
            continue  # nan, names
        if actual[name].default != value:
            return f"{name}={value!r}, the code's {actual[name].default!r}"
    return None


def test_api_md_signatures_are_the_codes():
    """Every signature docs/api.md writes out takes the call it shows: the same positional
    parameters in order, keyword parameters the function has, the same defaults (it showed
    ``DEM.sample``'s ``reference`` and ``Ortho.write``'s ``dtype`` as positional, which are
    keyword-only, and left out ``DEM.write``'s ``overwrite``)."""
    text = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    found = list(_documented_signatures(text))
    funcs = _api_signatures()
    assert {n for n, _ in found} == set(funcs), "a listed signature is no longer in api.md"
    problems = []
    for name, params in found:
        candidates = funcs[name] if isinstance(funcs[name], tuple) else (funcs[name],)
        why = [_check_signature(params, f) for f in candidates]
        if all(why):
            problems.append(f"{name}({params}): {why}")
    assert not problems, problems
