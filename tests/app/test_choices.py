"""Each option's choices live once (issue #23): the library's Literal aliases give the CLI's
``choices``, the configuration checks and the generated docs."""

import argparse

import pytest

from stereodem.cli import build_parser
from stereodem.config import Config, InputSettings, validate
from stereodem.core.errors import InputError
from stereodem.core.vertical import VERTICALS
from stereodem.docgen import configuration_markdown
from stereodem.ortho.choices import RESAMPLINGS, UNCERTAINTY_METHODS
from stereodem.ortho.drm import RESAMPLING
from stereodem.post import mosaic
from stereodem.post.choices import MOSAIC_METHODS
from stereodem.sensor.choices import ADJUST_MODELS, GENERIC_MODEL_NAMES, MODEL_SET_NAMES
from stereodem.sensor.estimation.adjust import MODEL_SETS
from stereodem.sensor.models import generic
from stereodem.stereo.settings import GRIDDING_METHODS, JITTER_AXES, MATCHERS


def _choices(command: str, option: str):
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    action = next(a for a in sub.choices[command]._actions if option in a.option_strings)
    return tuple(action.choices)


@pytest.mark.parametrize(
    "command, option, choices",
    [
        ("dem", "--matcher", MATCHERS),
        ("dem", "--gridding", GRIDDING_METHODS),
        ("dem", "--jitter-correction", JITTER_AXES),
        ("dem", "--dem-vertical", VERTICALS),
        ("filter", "--dem-vertical", VERTICALS),
        ("ortho", "--resampling", RESAMPLINGS),
        ("ortho", "--dem-vertical", VERTICALS),
        ("assess", "--ref-vertical", VERTICALS),
        ("uncertainty", "--method", UNCERTAINTY_METHODS),
        ("mosaic", "--method", MOSAIC_METHODS),
        ("adjust", "--model", ADJUST_MODELS),
    ],
)
def test_cli_choices_are_the_librarys(command, option, choices):
    assert _choices(command, option) == choices


def test_mosaic_methods_are_the_light_modules():
    assert mosaic.METHODS is MOSAIC_METHODS


def test_adjust_models_are_the_librarys():
    """The light table of `adjust --model` names is the library's: the fitted models' forms
    and the registry of built-in parameter sets (a test registering its own set removes it)."""
    assert generic.MODEL_NAMES is GENERIC_MODEL_NAMES
    assert tuple(generic._FORMS) == GENERIC_MODEL_NAMES
    assert tuple(sorted(MODEL_SETS)) == MODEL_SET_NAMES
    assert ADJUST_MODELS == (*sorted(MODEL_SETS), *generic.MODEL_NAMES, "bundle")


def test_ortho_kernels_cover_the_resampling_choices():
    assert set(RESAMPLING) == set(RESAMPLINGS)


@pytest.mark.parametrize(
    "section, key, value",
    [
        ("stereo.matching", "matcher", "bm"),
        ("stereo.gridding", "method", "median"),
        ("jitter", "axes", "yaw"),
        ("ortho", "resampling", "area"),
        ("uncertainty", "method", "exact"),
        ("ortho", "fill_dem_vertical", "navd88"),
    ],
)
def test_configuration_refuses_other_values_naming_the_choices(section, key, value):
    cfg = Config(InputSettings(left="l.tif", right="r.tif"), "out")
    owner = cfg
    for part in section.split("."):
        owner = getattr(owner, part)
    setattr(owner, key, value)
    with pytest.raises(InputError, match=rf"{key} must be .*got '{value}'"):
        validate(cfg)


def test_docs_list_the_literal_choices():
    text = configuration_markdown()
    assert '| `fill_dem_vertical` | {"geoid", "ellipsoid"}, optional |' in text
    assert "{" + ", ".join(f'"{m}"' for m in MATCHERS) + "}" in text
