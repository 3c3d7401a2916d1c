"""The sub-commands of the ``stereodem`` command line, in one table: name -> (module with
``add_parser``/``run``, one-line summary). ``stereodem --help`` lists them from here without
importing their modules (some are slow to import); each module's ``add_parser`` takes its
summary from here too."""

from __future__ import annotations

#: name -> (module, one-line summary), in the order ``stereodem --help`` lists them
COMMANDS = {
    "demo": ("stereodem.demo_cli", "simulate an ASTER-like pair and run the whole job on it"),
    "run": (
        "stereodem.run_cli",
        "run the whole job (stereo, filters, ortho, assessment) from a TOML file",
    ),
    "batch": ("stereodem.batch_cli", "run many scenes (configurations or granules), one job each"),
    "simulate": ("stereodem.simulate_cli", "simulate a stereo pair from a DEM and a texture"),
    "dem": ("stereodem.dem_cli", "stereo DEM from two images with sensor models"),
    "filter": ("stereodem.filter_cli", "blunder filters and hole filling of a stereo DEM"),
    "ortho": ("stereodem.ortho_cli", "orthorectify an image onto a DEM"),
    "assess": (
        "stereodem.assess_cli",
        "accuracy of a DEM against a reference DEM and check points",
    ),
    "coregister": (
        "stereodem.coregister_cli",
        "co-register a DEM to a reference DEM or altimetry points",
    ),
    "adjust": ("stereodem.adjust_cli", "adjust sensor models to GCPs / bundle-adjust a pair"),
    "compare-models": ("stereodem.compare_cli", "compare sensor models fitted to the same GCPs"),
    "uncertainty": (
        "stereodem.uncertainty_cli",
        "per-cell uncertainty and sensitivity maps of an orthoimage",
    ),
    "info": ("stereodem.info_cli", "describe an ASTER L1A granule"),
    "mosaic": (
        "stereodem.mosaic_cli",
        "one DEM from many: blended seams, statistics, bounded memory",
    ),
    "stack": (
        "stereodem.stack_cli",
        "stack DEMs of many dates: co-register, mask clouds, fit rates and volumes",
    ),
    "change": ("stereodem.change_cli", "elevation change between two DEMs, with its sigma map"),
}


def help_line(name: str) -> str:
    """The one-line summary of sub-command ``name``."""
    return COMMANDS[name][1]
