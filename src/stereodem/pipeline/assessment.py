"""The assessment stage (``stereodem assess``, and the last stage of ``stereodem run``):
:func:`assess_stage`, in a module of its own so that the ``assess`` command imports the
assessment without the stereo, filter and orthoimage stages of :mod:`.stages` (which
re-exports it): about 0.5 CPU s less before the command starts its work."""

from __future__ import annotations

from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.threads import job_threads
from stereodem.post.assess import assess_dem, reconcile_vertical

from ..config import Config


def assess_stage(
    cfg: Config,
    dem,
    out_dir,
    *,
    overwrite=True,
    provenance=None,
    error_analysis=None,
    analysis: bool = True,
    reference: DEM | None = None,
):
    """Accuracy report of ``dem`` (a :class:`DEM` or a path) against the reference DEM and
    check points of the configuration, written into ``out_dir``; returns (assessment, files).

    ``error_analysis`` (:class:`stereodem.post.error_analysis.ErrorAnalysisJob`) adds the
    stable-terrain error analysis section and its figures to the report (``analysis=False``:
    the job only says the stable terrain, ``exclude``, and the track of the co-registration,
    e.g. ``assess --coregister --exclude glaciers.gpkg``, or ``[assess] exclude`` when no job
    is given: no section). Its ``chain`` (else
    ``nuth_kaab`` when ``[assess] coregister``) is fitted once, on the job's stable terrain,
    and is the report's co-registration: the before/after tables are of the DEM after the
    whole chain, and the analysis is of that DEM."""
    from stereodem.post.report import write_report

    i, a = cfg.inputs, cfg.assess
    if not i.reference_dem:
        raise InputError("the assessment needs a reference DEM ([inputs] reference_dem, --ref)")
    dem = dem if isinstance(dem, DEM) else DEM.from_file(dem, vertical=i.dem_vertical)
    ref = (
        reference
        if reference is not None
        else DEM.from_file(i.reference_dem, vertical=i.reference_vertical)
    )
    kw = {} if a.slope_bins is None else dict(slope_bins=a.slope_bins)
    if error_analysis is None and a.exclude:  # [assess] exclude: the stable terrain only
        from stereodem.post.error_analysis import ErrorAnalysisJob

        error_analysis, analysis = ErrorAnalysisJob(exclude=list(a.exclude)), False
    chain = reconciled = None
    if error_analysis is not None:
        from stereodem.post import error_analysis as ea  # its variograms: only when asked

        # converted once (a full-grid geoid lookup): assess_dem is given it, not again
        reconciled = reconcile_vertical(dem, ref)
        dem_v = reconciled[0]
        # one chain for the report's co-registration section and the analysis: --chain, else
        # Nuth & Kääb with --coregister; fitted once, on the analysis's stable terrain and track
        text = error_analysis.chain or ("nuth_kaab" if a.coregister else None)
        if text:
            chain = ea.fit_chain(dem_v, ref, text, error_analysis)
    result = assess_dem(
        dem,
        ref,
        coregister=a.coregister or chain is not None,
        coregistration=chain,
        checkpoints=i.checkpoints,
        checkpoint_crs=i.checkpoints_crs,
        checkpoint_vertical=i.checkpoints_vertical,
        landcover=i.landcover,
        landcover_names={int(k): v for k, v in (a.landcover_names or {}).items()},
        elevation_bins=a.elevation_bins,
        threads=job_threads(cfg.run.workers),
        reconciled=reconciled,
        **kw,
    )
    extra = None
    if error_analysis is not None and analysis:
        section, plots = ea.analyse(dem_v, ref, error_analysis, chain=chain)

        def extra(out, ow):
            return "error_analysis", section, ea.write_figures(plots, out, overwrite=ow)

    files = write_report(
        result,
        out_dir,
        dem_heights=dem.heights,
        dem_transform=dem.transform,
        dem_crs=dem.crs,
        overwrite=overwrite,
        provenance=provenance,
        extra=extra,
    )
    return result, files
