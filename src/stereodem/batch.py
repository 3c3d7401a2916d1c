"""Many scenes, one job each, on a process pool or a ``dask.distributed`` cluster.

A *scene* is a TOML configuration (``stereodem run``'s) or an ASTER L1A granule (V004 ``.hdf``,
V003 ``.zip``/folder), the latter run with a template configuration (``--template``: every key
but ``[inputs] left/right`` and ``[output] dir``) or the defaults. Each scene writes into
``OUTDIR/<scene name>/`` exactly what ``stereodem run`` writes there.

* **Scheduling**: one task per scene, largest input first (a big scene started last would
  keep one core busy after the others are idle). Process pool: ``workers`` processes, each
  pinned to ``cores // workers`` threads (:mod:`stereodem.core.threads`), which it gives to its
  scene (its tiles then run in that many processes: ``[run] workers``). Dask: one task per
  scene on any worker (``--dask tcp://host:port`` or ``--dask local`` for a ``LocalCluster``),
  each worker pinned to its share of its node's cores; the scene's tiles run inside the task.
* **Resumable**: a scene whose folder holds a ``run.json`` with status ``ok`` is *skipped*
  (unless its configuration or template changed since: it then fails, naming the ``run.json``);
  one that failed or was interrupted runs again with its finished tiles reused (``--resume``
  semantics); ``overwrite`` recomputes every scene.
* **Status table**: ``OUTDIR/batch.json`` (rewritten atomically as scenes finish), one row per
  scene in OUTDIR: ``done`` / ``failed`` with its one-line reason / ``skipped`` / ``pending``,
  seconds, CPU seconds, output folder and the start of the batch that wrote the row
  (``batch_started``); a batch run again in OUTDIR merges its rows into the table by scene
  name (its own row wins for a scene it runs again; the other scenes' rows stay). ``summary``
  counts every row, ``this_run`` this batch's. A failing scene never stops the others.
* **OUTDIR** is under the one overwrite policy (:mod:`stereodem.outlock`, :data:`PRODUCTS`):
  new or empty, it is the batch's; holding a previous batch's ``batch.json`` it is continued
  (no ``--overwrite`` needed, nothing removed: ``--overwrite`` recomputes the scenes given);
  holding anything else it is refused without ``--overwrite``, and with it the batch writes
  beside those files unless one is named ``batch.json``. It is locked for the batch; each
  scene's folder is ``stereodem run``'s, under ``run``'s policy.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import tomllib

from stereodem.core import jsonutil
from stereodem.core.errors import InputError, StereodemError, not_found, one_line
from stereodem.core.pool import stop_pool
from stereodem.core.raster import write_text_atomic
from stereodem.core.threads import (
    cores,
    pool_initargs,
    pool_initializer,
    pool_size,
    register_dask_plugin,
    thread_budget,
    worker_threads,
)
from stereodem.stereo.execution import OtherJobTilesError

from .config import config_from_dict, load_config
from .outlock import Products, check_output_folder, is_marker, output_folder
from .pipeline.job import run

log = logging.getLogger(__name__)

LIST_SUFFIXES = (".txt", ".lst", ".list")
STATUS_FILE = "batch.json"
#: what a batch writes into OUTDIR itself (each scene's folder is ``stereodem run``'s): its
#: status table, which marks the folder as a batch's, continued by the next batch run there
PRODUCTS = Products((STATUS_FILE,), markers=(STATUS_FILE,), continues=True)
#: the counts of a status table, per status
STATUSES = ("done", "failed", "skipped", "pending")


@dataclass
class Scene:
    """One scene of a batch: its input (configuration or granule), its name (the output
    sub-folder) and, for granules, the template configuration."""

    name: str
    path: str
    kind: str  # "config" | "granule" | "missing"
    template: str | None = None
    size: int = 0  # bytes of its main input: the scheduling order


@dataclass
class SceneStatus:
    """A scene's row of the status table."""

    name: str
    input: str
    status: str  # "done" | "failed" | "skipped"
    reason: str = ""
    output: str = ""
    seconds: float = 0.0
    cpu_s: float = 0.0
    extra: dict = field(default_factory=dict)
    batch_started: str = ""  # when the batch that wrote the row started (UTC)


# ----------------------------------------------------------------------------- scenes


def expand_inputs(paths, template=None) -> list[Scene]:
    """The scenes named by ``paths``: configurations (``*.toml``), granules, and list files
    (``*.txt``/``*.lst``: one path per line, ``#`` comments, relative to the list). Names are
    the file stems, made unique with ``_2``, ``_3``, ...; a path that does not exist becomes a
    scene that fails as missing (:func:`~stereodem.core.errors.not_found`; the others still
    run). A list file that cannot be read, a scene given twice (it would be run twice) and a
    ``template`` that cannot be read as TOML are an :class:`InputError` (before any scene
    runs)."""
    if template is not None:
        _read_template(template)
    scenes, seen, given = [], {}, {}
    for p in _flatten(paths):
        path = Path(p)
        key = str(path.resolve())
        if key in given:
            raise InputError(f"{p}: scene given twice (also as {given[key]})")
        given[key] = p
        kind = (
            "missing"
            if not path.exists()
            else "config"
            if path.suffix.lower() == ".toml"
            else "granule"
        )
        stem = path.name if path.is_dir() else path.stem
        n = seen[stem] = seen.get(stem, 0) + 1
        name = stem if n == 1 else f"{stem}_{n}"
        size = _size(path) if kind == "granule" else _config_size(path) if kind == "config" else 0
        scenes.append(Scene(name, str(path), kind, template if kind == "granule" else None, size))
    if not scenes:
        raise InputError("batch: no scene given")
    return scenes


def _read_template(template) -> dict:
    """The template configuration's TOML tables (:class:`InputError` naming it when it cannot
    be read or parsed)."""
    t = Path(template)
    try:
        return tomllib.loads(t.read_text())
    except FileNotFoundError:
        raise InputError(not_found(t, "template configuration")) from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"{t}: cannot read the template configuration ({exc})") from None


def _flatten(paths):
    for p in paths:
        path = Path(p)
        if path.suffix.lower() in LIST_SUFFIXES:
            try:
                lines = path.read_text().splitlines()
            except FileNotFoundError:
                raise InputError(not_found(path, "scene list")) from None
            except (OSError, UnicodeDecodeError) as exc:
                raise InputError(f"{path}: cannot read the scene list ({exc})") from None
            for line in lines:
                line = line.split("#", 1)[0].strip()
                if line:
                    q = Path(line)
                    yield str(q if q.is_absolute() else path.parent / q)
        else:
            yield str(path)


def _size(path: Path) -> int:
    try:
        return (
            sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
            if path.is_dir()
            else path.stat().st_size
        )
    except OSError:
        return 0


def _config_size(path: Path) -> int:
    """Bytes of a configuration's images (0 when it cannot be read: it will fail later)."""
    try:
        cfg = load_config(path, output_dir=".")
    except Exception:  # noqa: BLE001 - a bad configuration fails in its own task, with its reason
        return 0
    return sum(_size(Path(p)) for p in (cfg.inputs.left, cfg.inputs.right) if p)


def scene_config(
    scene: Scene,
    out_dir,
    *,
    workers: int = 1,
    overwrite: bool = False,
    keep_tiles: bool | None = None,
):
    """The :class:`stereodem.config.Config` of one scene, writing into ``out_dir``;
    ``keep_tiles`` (None: the configuration's ``[run] keep_tiles``) overrides it."""
    if scene.kind == "missing":
        raise InputError(not_found(scene.path, "scene"))
    resume = not overwrite
    # absolute: the paths run.json records then name the same files from any folder
    # (:func:`done_with_other_settings` compares them)
    if scene.kind == "config":
        # the scene's folder is OUT/<name> whatever its [output] dir says, which it then
        # need not have (a configuration without it failed: "[output] needs 'dir'")
        cfg = load_config(
            Path(scene.path).absolute(),
            output_dir=out_dir,
            workers=workers,
            overwrite=overwrite,
            resume=resume,
            keep_tiles=keep_tiles,
        )
    else:
        _check_granule(scene.path)
        raw, base = {}, "."
        if scene.template:
            raw = _read_template(scene.template)
            base = Path(scene.template).absolute().parent
        raw.setdefault("inputs", {})
        raw["inputs"] = {k: v for k, v in raw["inputs"].items() if k not in ("left", "right")}
        raw["inputs"]["left"] = str(Path(scene.path).resolve())
        raw.pop("output", None)
        cfg = config_from_dict(
            raw,
            base=base,
            output_dir=out_dir,
            source=scene.template or "batch defaults",
            workers=workers,
            overwrite=overwrite,
            resume=resume,
            keep_tiles=keep_tiles,
        )
    cfg.output_dir = str(out_dir)
    return cfg


def _check_granule(path) -> None:
    """A scene that is no configuration must be an ASTER L1A granule: else an
    :class:`InputError` with the granule reader's reason and what a scene may be (a GeoTIFF
    or a folder given as a scene failed with "batch defaults: [inputs] needs 'right'")."""
    from stereodem.sensor.io.aster_l1a import is_aster_granule, open_aster_granule

    if is_aster_granule(path):
        return
    try:
        open_aster_granule(path)  # not a granule: the reader says why
    except InputError as exc:
        raise InputError(
            f"{exc}; a batch scene is an ASTER L1A granule or a configuration (.toml)"
        ) from None


def is_done(out_dir) -> bool:
    """Whether a scene's folder holds a finished job (``run.json`` with status ``ok``)."""
    try:
        return json.loads((Path(out_dir) / "run.json").read_text()).get("status") == "ok"
    except (OSError, ValueError, AttributeError):
        return False


#: settings of a scene's configuration, with their paths: what its products depend on
_PATHS = {
    "inputs": ("left", "right", "left_model", "right_model", "seed_dem", "reference_dem")
    + ("checkpoints", "landcover", "dem", "images"),
    "uncertainty": ("covariance",),
    "ortho": ("fill_dem",),
}


def _settings(config: dict) -> dict:
    """A configuration's :meth:`~stereodem.config.Config.to_dict` as ``run.json`` holds it,
    without how it was run (``[run]``, the output folder) and with absolute paths."""
    d = json.loads(jsonutil.dumps(config))
    for section, keys in _PATHS.items():
        table = d.get(section) or {}
        for k in keys:
            v = table.get(k)
            if isinstance(v, str):
                table[k] = os.path.abspath(v)
            elif isinstance(v, list):
                table[k] = [os.path.abspath(p) if isinstance(p, str) else p for p in v]
    return {k: v for k, v in d.items() if k not in ("run", "output")}


def done_with_other_settings(out_dir, cfg) -> bool:
    """Whether the finished job in ``out_dir`` was run with other settings or inputs than the
    scene's configuration ``cfg`` now has (it was edited since). False when ``run.json`` does
    not record them. Only the keys both record are compared: a key a later version added
    (or removed) is no edit of the user's, and would otherwise redo every scene."""
    try:
        old = json.loads((Path(out_dir) / "run.json").read_text()).get("config")
    except (OSError, ValueError, AttributeError):
        return False
    if not isinstance(old, dict):
        return False
    was, now = _settings(old), _settings(cfg.to_dict())
    for section in was.keys() & now.keys():
        a, b = was[section], now[section]
        if not (isinstance(a, dict) and isinstance(b, dict)):
            if a != b:
                return True
            continue
        if any(a[k] != b[k] for k in a.keys() & b.keys()):
            return True
    return False


# ----------------------------------------------------------------------------- one scene


def run_scene(
    scene: Scene,
    out_root,
    workers: int = 1,
    overwrite: bool = False,
    keep_tiles: bool | None = None,
) -> SceneStatus:
    """Run one scene into ``out_root/<name>``; never raises: a failure is a ``failed`` row
    with a one-line reason. Runs in a pool worker or a Dask task (picklable arguments)."""
    out = Path(out_root) / scene.name
    row = SceneStatus(scene.name, scene.path, "done", output=str(out))
    if not overwrite and is_done(out):
        # a scene whose configuration (or template) changed since was skipped: its products,
        # of the old settings, were reported as done
        try:
            cfg = scene_config(scene, out, workers=workers, keep_tiles=keep_tiles)
            changed = done_with_other_settings(out, cfg)
        except StereodemError as exc:
            row.status, row.reason = "failed", _one_line(exc)
            return row
        if not changed:
            row.status = "skipped"
            row.reason = "already done (run.json status ok)"
            return row
        row.status = "failed"
        row.reason = (
            f"{out / 'run.json'}: done with other settings or inputs than {scene.path} "
            "now has; pass --overwrite to recompute (or use another -o)"
        )
        return row
    t0, c0 = time.perf_counter(), _cpu()
    try:
        cfg = scene_config(scene, out, workers=workers, overwrite=overwrite, keep_tiles=keep_tiles)
        info = run(cfg)
        row.extra = {
            "stages": {k: v.get("seconds") for k, v in info.get("stages", {}).items()},
            "headline": info.get("headline"),
        }
    except OtherJobTilesError as exc:
        # a failed or interrupted scene edited since: its tiles are not reused; run's message
        # said "run again without --resume", a flag batch does not have
        row.status = "failed"
        row.reason = (
            f"{exc.cache_dir}: the cached tiles belong to a run with other inputs or settings "
            f"than {scene.path} now has; pass --overwrite to recompute that scene (or use "
            "another -o)"
        )
    except StereodemError as exc:
        row.status, row.reason = "failed", _one_line(exc)
    except MemoryError:
        row.status, row.reason = "failed", "out of memory"
    except Exception as exc:  # noqa: BLE001 - one scene's bug must not stop the batch
        row.status, row.reason = "failed", f"{type(exc).__name__}: {_one_line(exc)}"
    row.seconds = round(time.perf_counter() - t0, 3)
    row.cpu_s = round(_cpu() - c0, 2)
    return row


def _cpu() -> float:
    """CPU seconds of this process and its finished children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _one_line(exc) -> str:
    # the command line's words, as its other reasons ("pass --overwrite")
    return one_line(exc, "command line")


# ----------------------------------------------------------------------------- the batch


def run_batch(
    scenes,
    out_root,
    *,
    workers: int | None = None,
    dask: str | None = None,
    overwrite: bool = False,
    keep_tiles: bool | None = None,
    progress=None,
) -> dict:
    """Run ``scenes`` (:func:`expand_inputs`) into ``out_root``; returns the status table
    (also written to ``out_root/batch.json``): the rows of a previous batch in ``out_root``
    with this batch's merged in by scene name (``this_run``: this batch's counts).

    ``out_root`` is under the one overwrite policy (:data:`PRODUCTS`): new, empty or a
    previous batch's (continued); a folder holding other files is refused without
    ``overwrite`` (:class:`~stereodem.core.errors.OutputExistsError`).

    ``workers``: scenes at once on the process pool (default: all cores), or the
    ``LocalCluster``'s worker processes with ``dask="local"``; ``dask``: a scheduler address
    (``tcp://...``), ``"local"``, or a ``Client``. ``keep_tiles``: whether each scene keeps
    its tile cache once done (None: its configuration's ``[run] keep_tiles``).
    ``progress(row)`` is called per finished scene.
    """
    inputs = [s.path for s in scenes] + [s.template for s in scenes if s.template]
    # before any work: under a file, in a read-only place (/proc), a folder of the user's
    check_output_folder(out_root, PRODUCTS, overwrite=overwrite, inputs=inputs)
    with output_folder(out_root, PRODUCTS, overwrite=overwrite, inputs=inputs) as out_root:
        return _run_batch_in(
            scenes, out_root, workers, dask, (overwrite, keep_tiles), progress=progress
        )


def _run_batch_in(scenes, out_root, workers, dask, scene_options, progress=None) -> dict:
    """:func:`run_batch` in its locked folder; ``scene_options``: :func:`run_scene`'s
    ``(overwrite, keep_tiles)``."""
    order = sorted(scenes, key=lambda s: -s.size)  # largest first
    n = min(pool_size(workers), len(order))
    rows: dict[str, SceneStatus] = {}
    t0 = time.perf_counter()
    backend = "dask" if dask is not None else "pool" if n > 1 else "serial"
    started = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    table = {"started": started, "backend": backend, "workers": n, "cores": cores()}
    earlier = earlier_rows(out_root)

    def write():
        return _write_table(out_root, scenes, rows, table, time.perf_counter() - t0, earlier)

    def collect(row: SceneStatus):
        row.batch_started = started
        rows[row.name] = row
        write()
        if progress:
            progress(row)

    # the table first: the folder is a batch's (and the scenes pending) even if the batch is
    # killed before its first scene finishes
    write()
    try:
        if dask is not None:
            _run_dask(order, out_root, dask, n, scene_options, collect)
        elif n <= 1:
            with thread_budget(1):
                for s in order:
                    collect(run_scene(s, out_root, 1, *scene_options))
        else:
            _run_pool(order, out_root, n, worker_threads(n), scene_options, collect)
    except BaseException:
        # interrupted (Ctrl-C, SIGTERM): the table still says which scenes are done and which
        # are pending (a run interrupted before its first scene finished left none at all)
        write()
        raise
    return write()


def earlier_rows(out_root) -> dict[str, dict]:
    """The rows of the status table a previous batch left in ``out_root`` (by scene name;
    empty when there is none). A table that is not stereodem's is not read (the overwrite
    policy refuses such a folder before); one without rows is taken as empty, with a
    warning."""
    path = Path(out_root) / STATUS_FILE
    if not is_marker(path):
        return {}
    try:
        scenes = json.loads(path.read_text(encoding="utf-8")).get("scenes")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        scenes = None
    if not isinstance(scenes, list):
        log.warning("%s: no scene rows in it; the table starts afresh", path)
        return {}
    return {r["name"]: r for r in scenes if isinstance(r, dict) and isinstance(r.get("name"), str)}


def scene_pool(n: int, threads: int) -> ProcessPoolExecutor:
    """The scenes' process pool: ``n`` spawned workers pinned to ``threads`` threads, logging
    as the main process does (:mod:`stereodem.core.worker_logging`: "WARNING logger:
    message" as in a serial run, not the message alone)."""
    return ProcessPoolExecutor(
        max_workers=n,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=pool_initializer,
        initargs=pool_initargs(threads),
    )


def _run_pool(order, out_root, n, threads, scene_options, collect):
    """The scenes on a process pool; ``scene_options``: :func:`run_scene`'s ``(overwrite,
    keep_tiles)``."""
    ex = scene_pool(n, threads)
    try:
        futs = {ex.submit(run_scene, s, out_root, threads, *scene_options): s for s in order}
        for f in as_completed(futs):
            s = futs[f]
            try:
                collect(f.result())
            except Exception as exc:  # noqa: BLE001 - a worker died (killed, out of memory)
                collect(
                    SceneStatus(
                        s.name,
                        s.path,
                        "failed",
                        reason=f"worker died: {type(exc).__name__}: {_one_line(exc)}",
                        output=str(Path(out_root) / s.name),
                    )
                )
    except BaseException:
        stop_pool(ex)
        raise
    ex.shutdown(wait=True)


def _run_dask(order, out_root, address, n, scene_options, collect):
    """The scenes as tasks of a Dask cluster; ``scene_options`` as :func:`_run_pool`'s."""
    try:
        from dask.distributed import Client
        from dask.distributed import as_completed as dask_completed
    except ImportError:
        raise InputError("--dask needs dask.distributed: pip install 'stereodem[dask]'") from None
    from stereodem.core.dask_threads import local_cluster, quiet_distributed_logging

    quiet_distributed_logging()
    cluster = None
    if address == "local":
        cluster = local_cluster(n)
        client = Client(cluster)
    elif hasattr(address, "submit"):
        client = address
    else:
        from stereodem.core.dask_threads import connect

        client = connect(address)
    try:
        register_dask_plugin(client, own_workers=cluster is not None)
        # scenes run their tiles inside the task (Dask workers are daemon processes: no pool)
        futs = {
            client.submit(
                run_scene,
                s,
                str(out_root),
                1,
                *scene_options,
                pure=False,
                key=f"stereodem-scene-{s.name}-{time.monotonic_ns()}",
            ): s
            for s in order
        }
        for f in dask_completed(futs):
            s = futs[f]
            try:
                collect(f.result())
            except Exception as exc:  # noqa: BLE001 - a worker lost, a task cancelled
                collect(
                    SceneStatus(
                        s.name,
                        s.path,
                        "failed",
                        reason=f"task lost: {type(exc).__name__}: {_one_line(exc)}",
                        output=str(Path(out_root) / s.name),
                    )
                )
    finally:
        if client is not address:
            client.close()
        if cluster is not None:
            cluster.close()


def _write_table(out_root, scenes, rows, table, seconds, earlier) -> dict:
    """``batch.json``: the ``earlier`` rows with this batch's (``rows``, else ``pending``, or
    the earlier row while this batch has not reached the scene) merged in by scene name, this
    batch's own at their place, new scenes after them; the times are this batch's,
    ``summary`` counts every row, ``this_run`` this batch's."""
    now = {
        s.name: asdict(
            rows[s.name]
            if s.name in rows
            else SceneStatus(
                s.name,
                s.path,
                "pending",
                output=str(Path(out_root) / s.name),
                batch_started=table["started"],
            )
        )
        for s in scenes
    }
    mine = list(now.values())
    # a scene this batch has not reached keeps its earlier row (its products are there: a
    # batch interrupted before it must not turn a done scene into a pending one)
    listed = []
    for name, row in earlier.items():
        this = now.pop(name, None)
        listed.append(this if name in rows else row)
    listed += list(now.values())
    result = {
        **table,
        "seconds": round(seconds, 3),
        "sum_scene_seconds": round(sum(r["seconds"] for r in mine), 3),
        "cpu_s": round(sum(r["cpu_s"] for r in mine), 2),
        "summary": _counts(listed),
        "this_run": {"scenes": len(mine), **_counts(mine)},
        "scenes": listed,
    }
    result = jsonutil.stamped(result)
    write_text_atomic(Path(out_root) / STATUS_FILE, jsonutil.dumps(result), overwrite=True)
    return result


def _counts(rows) -> dict:
    return {k: sum(r.get("status") == k for r in rows) for k in STATUSES}


def status_text(status: str, reason: str = "", seconds: float = 0.0) -> str:
    """How a scene's status reads for people, in the progress lines and the status table:
    "done in 12.3 s", "skipped: already done (run.json status ok)", "FAILED: REASON", "not
    run" (the reason after a colon: one level of brackets, never "skipped (already done
    (...))"). batch.json keeps ``status`` and ``reason`` as fields."""
    if status == "done":
        return f"done in {seconds:.1f} s"
    if status == "pending":
        return "not run"
    word = "FAILED" if status == "failed" else status
    return f"{word}: {reason}" if reason else word


def summary_lines(result: dict) -> list[str]:
    """The status table for people: one line per scene of this batch, then its totals and
    how many of the table's rows it wrote (the others are earlier batches' in the folder)."""
    lines = []
    mine = [r for r in result["scenes"] if r.get("batch_started") == result.get("started")]
    for r in mine:
        what = status_text(r["status"], r["reason"], r["seconds"])
        lines.append(f"  {r['name']:24s} {what}")
    c = result.get("this_run", result["summary"])
    total, earlier = len(result["scenes"]), len(result["scenes"]) - len(mine)
    rows = f"{total} row(s), {len(mine)} from this run" + (
        f", {earlier} from earlier runs" if earlier else ""
    )
    lines.append(
        f"{len(mine)} scene(s): {c['done']} done, {c['failed']} failed, "
        f"{c['skipped']} skipped, in {result['seconds']:.1f} s on {result['backend']} "
        f"with {result['workers']} worker(s); status table in {STATUS_FILE}: {rows}"
    )
    return lines
