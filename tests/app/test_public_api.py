"""The public API in one place (issue #23): every name of ``stereodem.__all__`` resolves, to
the object of its defining module, and ``import stereodem`` stays light (lazy, PEP 562)."""

import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

import stereodem
from stereodem.core import errors
from stereodem.core.errors import InputError
from stereodem.post import coreg
from stereodem.sensor.simulation.simulate import simulate_scene


@pytest.mark.parametrize("name", [n for n in stereodem.__all__ if n != "__version__"])
def test_every_public_name_resolves_to_its_module(name):
    value = getattr(stereodem, name)
    assert value is getattr(importlib.import_module(stereodem._API[name]), name)


def test_unknown_names_are_attribute_errors():
    with pytest.raises(AttributeError, match="no_such_thing"):
        stereodem.no_such_thing  # noqa: B018


def test_import_stereodem_loads_no_heavy_library():
    code = (
        "import sys, stereodem; heavy = {'numpy', 'cv2', 'rasterio', 'scipy', 'pyproj'} "
        "& set(sys.modules); print(sorted(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_the_run_pipeline_imports_no_dataframe_or_plotting_library():
    """What ``stereodem run`` imports before its first stage (every run and every worker
    start pays it): no pandas (pyogrio imports it; vectors are read only when given), no
    matplotlib (the report's figures import it when drawn) and no scipy.stats (0.2 s; the
    adjustment's quantiles come from scipy.special)."""
    code = (
        "import sys, stereodem.run_cli, stereodem.pipeline.job; "
        "print(sorted({'pandas', 'matplotlib', 'scipy.stats'} & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_the_assess_command_imports_no_stereo_pipeline():
    """``stereodem assess`` imports its stage (``pipeline.assessment``), its configuration and
    its report without the stereo, filter and orthoimage stages, the ASTER reader (SciPy's
    interpolation) or the error analysis's variograms (used only with --error-analysis):
    0.27 s of imports less before the command's work (1391 -> 1123 modules)."""
    code = (
        "import sys, stereodem.assess_cli, stereodem.config, stereodem.pipeline.assessment, "
        "stereodem.post.report; print(sorted({'stereodem.pipeline.stages', "
        "'stereodem.stereo.pipeline', 'stereodem.sensor.io.aster_l1a', 'scipy.interpolate', "
        "'stereodem.post.error_analysis', 'stereodem.post.spatialstats'} & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_every_error_class_is_public():
    """Every exception class of ``stereodem.core.errors`` is a public name. Before,
    ``CRSError``, ``SensorModelError``, ``RPCError``, ``DEMCoverageError``, ``NoOverlapError``
    and ``ConvergenceError`` were missing from ``stereodem.__all__``: ``DEM(h, t, None)``
    raised a ``CRSError`` that ``from stereodem import CRSError`` could not import."""
    classes = {
        name
        for name, value in vars(errors).items()
        if isinstance(value, type) and issubclass(value, Exception)
    }
    assert classes <= set(stereodem.__all__)
    assert all(getattr(stereodem, n) is getattr(errors, n) for n in classes)


def _subclasses(cls):
    for sub in cls.__subclasses__():
        yield sub
        yield from _subclasses(sub)


def test_every_error_the_public_functions_raise_is_public():
    """Every :class:`StereodemError` subclass of the library, wherever it is defined, is a
    public name. ``make_dem`` raised ``SparseMatchError`` (too few sparse matches) and
    ``stereodem.run`` ``SuspectResultError`` and ``OutputLockedError``, which
    ``from stereodem import ...`` could not import (only ``stereodem.core.errors``' classes
    were public)."""
    for name in stereodem.__all__:  # every module the public names live in, and its imports
        getattr(stereodem, name)
    found = {
        c.__name__: c
        for c in _subclasses(errors.StereodemError)
        if c.__module__.startswith("stereodem.")
    }
    assert {"SparseMatchError", "SuspectResultError", "OutputLockedError"} <= set(found)
    assert set(found) <= set(stereodem.__all__)
    assert all(getattr(stereodem, n) is c for n, c in found.items())


@pytest.mark.parametrize("cfg", ["job.toml", None])
def test_run_given_no_config_says_what_it_takes(cfg):
    """``stereodem.run("job.toml")`` (or None) failed with an AttributeError from inside the
    job ('str' object has no attribute 'output_dir')."""
    with pytest.raises(stereodem.InputError, match="expected a Config.*load_config"):
        stereodem.run(cfg)


@pytest.mark.parametrize("name", ["read_image", "load_model", "load_config"])
def test_readers_given_no_path_say_so(name):
    """``read_image(None)``, ``load_model(None)`` and ``load_config(None)`` raised pathlib's or
    rasterio's TypeError."""
    with pytest.raises(stereodem.InputError, match="expected a file path, got NoneType"):
        getattr(stereodem, name)(None)


@pytest.mark.parametrize("size", [50, (50,), ("a", 60), (60.5, 60)])
def test_simulate_scene_given_a_bad_size_says_so(size):
    """``simulate_scene(size=50)`` raised a TypeError from inside ('int' object is not
    subscriptable)."""
    with pytest.raises(InputError, match="size must be \\(width, height\\) in pixels"):
        simulate_scene("frame", size=size)


def test_the_coregistration_steps_are_public():
    """Every step ``parse_chain`` knows, the chain type and the points reference are public
    names, documented in docs/api.md (``stereodem.NuthKaab`` was an AttributeError: the
    steps lived only in ``stereodem.post.biascorr``)."""
    names = {cls.__name__ for cls in coreg._registry().values()}
    names |= {"Coreg", "CoregChain", "parse_chain", "AltimetryPoints", "read_points"}
    assert names <= set(stereodem.__all__)
    api = (Path(__file__).resolve().parents[2] / "docs" / "api.md").read_text(encoding="utf-8")
    assert not [n for n in names if not re.search(rf"\b{n}\b", api)]
    chain = stereodem.NuthKaab() + stereodem.Deramp(1)
    assert isinstance(chain, stereodem.CoregChain) and repr(chain) == "NuthKaab() + Deramp(1)"
