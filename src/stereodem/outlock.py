"""One job per output folder: an exclusive lock, products replaced only on request, inputs
never among the outputs. The one overwrite policy of every command that writes into a folder.

The policy (:func:`check_output_folder`, applied before any work and again under the lock by
:func:`output_folder`); each command declares its products (:class:`Products`):

* ``-o`` is a folder or can be created;
* no input is one of the command's products in the folder, even with ``--overwrite``;
* without ``--overwrite`` a non-empty folder is refused, naming its products (or its files);
* with ``--overwrite`` the command's products of a previous stereodem run (a folder holding one
  of its markers, e.g. ``run.json``, with stereodem's stamp in it: :func:`is_marker`; a file of
  the user's of that name is not one) are replaced when the job succeeds: set aside until then,
  and put back if it stops before writing its own; in a folder of the user's the products go
  beside the user's files as long as none of them has a product's name (else refused, naming
  it); a file of another name is never touched;
* a folder holding what a run of the same job left when it did not finish (its marker, written
  by stereodem, says ``failed``, ``interrupted`` or ``running`` and records the same input
  files: :func:`is_unfinished_run`) is a rerun's without ``--overwrite``: those products are
  set aside and replaced as ``--resume`` sets them aside (put back if the rerun stops before
  writing its own); another job's products, or a finished run's, still need ``--overwrite``;
* a command whose runs continue the previous one in its folder (``Products.continues``:
  ``batch``) takes a folder holding its marker as it is, without ``--overwrite`` and without
  removing anything (it replaces what it recomputes); any other non-empty folder is under the
  rules above.

:class:`OutputLock` holds ``OUT/.stereodem.lock`` with ``fcntl.flock`` (exclusive,
non-blocking) for the life of a job. The kernel drops the lock when the process dies, however
it dies, so a lock file left by a killed run (stale) is simply taken over; the file records
the holder's PID and host for the message a second job gets. The lock file is removed on
release.

:func:`output_folder` is what the commands use: it checks the folder, takes the lock, then,
with ``overwrite``, sets the products of the previous job aside until the job has written its
own (only in a folder that a stereodem job wrote, recognised by its ``run.json``,
``dem_report.json`` or tile cache manifest, read: each carries the version of stereodem that
wrote it): deleted when the job succeeds, put back if it stops before writing any of its own
(a failed rerun loses nothing); on ``resume`` it does the same but keeps the tile cache in
place. In a
folder of the user's (e.g. the one holding the inputs) it writes the products beside the
user's files only when none of them has a product's name: nothing of the user's is replaced
or removed. If the job fails before writing anything, a
folder it created is removed again.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import shutil
import socket
import time
from dataclasses import dataclass
from pathlib import Path

from stereodem.core.errors import InputError, OutputExistsError

log = logging.getLogger(__name__)

__all__ = [
    "LOCK_NAME",
    "OutputLock",
    "OutputLockedError",
    "output_folder",
    "remove_products",
    "restore_products",
    "set_aside_products",
    "staged",
    "is_stereodem_output",
    "is_unfinished_run",
    "job_inputs",
    "check_not_an_input",
    "check_output_folder",
    "Products",
    "JOB",
    "PRODUCTS",
]

LOCK_NAME = ".stereodem.lock"
#: the writability probe a job starting in the folder leaves there for an instant
PROBE_PREFIX = ".stereodem-probe-"
#: the hidden folders of a job in its output folder: the previous job's products set aside
#: (:func:`set_aside_products`) and a product folder being built (:func:`staged`); what a
#: killed job left of them is one of every command's products (:class:`Products`)
REMOVING_PREFIX = ".stereodem-removing-"

#: what a stereodem job (``dem``, ``run``, ``demo``) writes into its output folder (files and
#: folders, glob patterns)
PRODUCTS = (
    "run.json",
    "dem_report.json",
    "dem.tif",
    "dem_edit_mask.tif",
    "score.tif",
    "count.tif",
    "dem.las",
    "dem.laz",
    "raygap.tif",
    "nmad.tif",
    "dem_sigma_vertical.tif",
    "ortho_*.tif",
    "raw",
    "assess",
    "tiles",
    "demo.toml",
    "scene",
    "result",
    # what a job that was killed while it deleted its predecessor's products left
    REMOVING_PREFIX + "*",
)
#: files that mark a folder as a stereodem output
MARKERS = (
    "run.json",
    "dem_report.json",
    "tiles/job.json",
    "demo.toml",
    "stack.json",
    "change.json",
)
#: what a marker's ``status`` says of a job that did not finish (``running``: one killed
#: outright, whose lock the kernel dropped; read under the lock, no job is running there)
UNFINISHED = ("failed", "interrupted", "running")


@dataclass(frozen=True)
class Products:
    """What a command writes into its output folder: ``names`` (file or folder names, glob
    patterns) and ``markers``, the names of which one in the folder, when stereodem wrote it
    (:func:`is_marker`: its record carries stereodem's version), marks the folder as written by
    a previous run of the command (whose products ``--overwrite`` then replaces).

    ``continues``: a run continues the previous one in its folder (``batch``: done scenes
    skipped, the status table merged), so a folder holding one of the markers is taken as it
    is, without ``--overwrite``, and nothing in it is removed or set aside."""

    names: tuple
    markers: tuple
    continues: bool = False

    def __post_init__(self):
        # a GeoTIFF's GDAL side-car is part of it (core.raster.atomic_path moves it with the
        # file), and what a job killed while it deleted its predecessor's products left is a
        # product too
        more = [f"{n}.aux.xml" for n in self.names if n.endswith(".tif")]
        more += [REMOVING_PREFIX + "*"]
        names = (*self.names, *(n for n in more if n not in self.names))
        object.__setattr__(self, "names", names)


#: the products of a stereodem job (``dem``, ``run``, ``demo``)
JOB = Products(PRODUCTS, MARKERS)


class OutputLockedError(OutputExistsError):
    """Another job holds the output folder."""


class OutputLock:
    """Exclusive lock of an output folder for one job (a context manager).

    Raises :class:`OutputLockedError` naming the holder's PID when another process holds it.
    """

    def __init__(self, folder):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self._fd = None

    def acquire(self):
        for _ in range(50):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                if exc.errno not in (errno.EAGAIN, errno.EACCES):
                    raise
                raise OutputLockedError(
                    f"{self.folder}: another stereodem job is writing this folder "
                    f"({self._holder()}); wait for it or choose another -o"
                ) from None
            # the holder may have released and removed the file between our open and flock:
            # then we locked an unlinked file; try again with the current one
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.write(
                    fd,
                    json.dumps(
                        {
                            "pid": os.getpid(),
                            "host": socket.gethostname(),
                            "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
                        }
                    ).encode(),
                )
                self._fd = fd
                return self
            os.close(fd)
        raise OutputLockedError(f"{self.folder}: cannot take the output lock (contended)")

    def _holder(self) -> str:
        try:
            info = json.loads(self.path.read_text() or "{}")
            return f"PID {info['pid']} on {info.get('host', '?')}, since {info.get('started', '?')}"
        except (OSError, ValueError, KeyError, TypeError):
            return "holder unknown"

    def release(self):
        if self._fd is None:
            return
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)  # unlink while locked: no one can lock it meanwhile
        os.close(self._fd)  # closing drops the flock
        self._fd = None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
        return False


#: the first line of the configuration ``stereodem demo`` writes (``demo.toml``, a marker)
DEMO_TOML_STAMP = "# written by 'stereodem demo'"


def is_marker(path) -> bool:
    """Whether ``path`` (a marker's name in a folder) is a record stereodem wrote, not a file
    of the user's of that name: a JSON record carrying :data:`~stereodem.core.jsonutil.STAMP`
    (the version that wrote it, :func:`~stereodem.core.jsonutil.is_stamped`), or the demo's
    configuration with its first line (:data:`DEMO_TOML_STAMP`)."""
    from stereodem.core.jsonutil import is_stamped

    path = Path(path)
    try:
        if not path.is_file():
            return False
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return False
    if path.suffix == ".toml":
        return text.startswith(DEMO_TOML_STAMP)
    try:
        return is_stamped(json.loads(text))
    except ValueError:
        return False


def is_stereodem_output(folder, markers=MARKERS) -> bool:
    """Whether ``folder`` holds the products of a stereodem job (one of ``markers`` that
    stereodem wrote, :func:`is_marker`: a file of the user's of that name does not count), or
    what a job killed while they were set aside left (:func:`set_aside_products`)."""
    folder = Path(folder)
    return any(is_marker(folder / m) for m in markers) or any(folder.glob(REMOVING_PREFIX + "*"))


def job_inputs(inputs) -> list[str]:
    """A job's input files as its marker records them (``"inputs"``): resolved, sorted, once
    each; :func:`is_unfinished_run` compares a rerun's with them."""
    return sorted({str(Path(p).resolve()) for p in inputs if p})


def is_unfinished_run(folder, products: Products, inputs) -> bool:
    """Whether ``folder`` holds what a run of the same job left when it did not finish: one of
    ``products.markers``, written by stereodem (:func:`is_marker`), whose ``status`` is one of
    :data:`UNFINISHED` and whose ``inputs`` are this job's (:func:`job_inputs`). A rerun then
    replaces them without ``--overwrite``; a finished run's products, another job's and a
    file of the user's are not such leftovers."""
    ins = job_inputs(inputs)
    if not ins:
        return False
    for name in products.markers:
        record = _unfinished_record(Path(folder) / name)
        if record is not None and record.get("inputs") == ins:
            return True
    return False


def _unfinished_record(path: Path) -> dict | None:
    """The record in ``path`` when it is a marker stereodem wrote (:func:`is_marker`) whose
    ``status`` is one of :data:`UNFINISHED` (a job that failed, was interrupted or is still
    running), else None."""
    if not is_marker(path):
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if isinstance(record, dict) and record.get("status") in UNFINISHED:
        return record
    return None


def _product_paths(folder: Path, keep_tiles: bool, names=PRODUCTS):
    for pattern in names:
        if keep_tiles and pattern == "tiles":
            continue
        yield from folder.glob(pattern)


def remove_products(folder, *, keep_tiles: bool, products: Products = JOB) -> list[str]:
    """Remove the previous job's ``products`` from ``folder`` (the tile cache too unless
    ``keep_tiles``); other files are left alone. Returns the names removed."""
    removed, paths = _products_to_remove(Path(folder), keep_tiles, products)
    for p in paths:
        _delete(p)
    return removed


@contextlib.contextmanager
def staged(path):
    """Build a product folder (a Zarr store) under a hidden name beside ``path`` and move it
    into place when the block succeeds; yields the hidden path.

    A job that fails or is stopped while building it leaves no half-built store under the
    product's name (it is removed), so the previous job's products it set aside come back
    whole (:func:`restore_products`); what a killed job left under the hidden name goes with
    the next ``--overwrite`` or rerun, as one of the products (:data:`REMOVING_PREFIX`)."""
    path = Path(path)
    tmp = path.parent / f"{REMOVING_PREFIX}{path.name}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    try:
        tmp.rename(path)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise OutputExistsError(f"{path}: cannot be moved into place ({exc.strerror})") from None


def set_aside_products(
    folder, *, products: Products = JOB, keep_tiles: bool = True, verb: str = "set aside"
) -> Path | None:
    """Move the previous job's ``products`` (but its tile cache with ``keep_tiles``) into a
    hidden folder of ``folder`` (a rename each: out of the job's way at once), for a job that
    replaces them (``--overwrite``) or continues it (``--resume``): the job may still refuse
    the tiles or fail before writing anything, and the previous products are then put back
    (:func:`restore_products`); the job that succeeds deletes them.
    Returns the hidden folder (None: nothing to set aside); ``verb`` words the log line. A job
    killed meanwhile leaves the hidden folder, which the next ``--overwrite`` removes as one of
    the products (:data:`PRODUCTS`)."""
    folder = Path(folder)
    _, paths = _products_to_remove(folder, keep_tiles, products, verb=verb)
    if not paths:
        return None
    aside = folder / f"{REMOVING_PREFIX}{os.getpid()}-{time.monotonic_ns()}"
    moved = []
    try:
        aside.mkdir()
        for p in paths:
            p.rename(aside / p.name)
            moved.append(p)
    except OSError as exc:  # as they were, and a one-line refusal
        for p in moved:
            with contextlib.suppress(OSError):
                (aside / p.name).rename(p)
        with contextlib.suppress(OSError):
            aside.rmdir()
        raise OutputExistsError(
            f"{folder}: cannot set the previous job's products aside ({exc.strerror})"
        ) from None
    return aside


def restore_products(folder, aside: Path, products: Products = JOB) -> bool:
    """Put the products :func:`set_aside_products` moved into ``aside`` back into ``folder``
    when the job wrote none of them (it failed or was refused before writing anything), else
    delete them (the job's own are there: mixing the two would make a folder no job wrote).
    A marker of ``products`` that only records the job's failure (``stack.json`` saying
    ``failed``: :data:`UNFINISHED`) is not a product of it: it gives way to the previous
    products, which come back whole. Returns whether they were put back."""
    folder, aside = Path(folder), Path(aside)
    names = [p.name for p in aside.iterdir()]
    clash = [n for n in names if (folder / n).exists() or (folder / n).is_symlink()]
    if any(n not in products.markers or _unfinished_record(folder / n) is None for n in clash):
        shutil.rmtree(aside, ignore_errors=True)
        return False
    for n in clash:  # the failed job's own record of its failure
        (folder / n).unlink()
    for n in names:
        (aside / n).rename(folder / n)
    aside.rmdir()
    log.warning(
        "%s: the job stopped before writing its products: the previous job's %s are kept",
        folder,
        ", ".join(sorted(names)),
    )
    return True


def _products_to_remove(
    folder: Path, keep_tiles: bool, products: Products = JOB, verb: str = "removed"
):
    paths = sorted(set(_product_paths(folder, keep_tiles, products.names)))
    removed = [p.name for p in paths]
    if removed:
        log.info("%s: %s the previous job's %s", folder, verb, ", ".join(removed))
    return removed, paths


def remove_tile_cache(folder) -> bool:
    """Remove the tile cache ``folder/tiles`` of a finished job (its tiles and the points a
    point cloud was merged from); returns whether there was one."""
    cache = Path(folder) / "tiles"
    if not (cache.exists() or cache.is_symlink()):
        return False
    _delete(cache)
    return True


def _delete(p: Path):
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    else:
        p.unlink()


def check_not_an_input(outputs, inputs, products: Products = JOB):
    """:class:`InputError` if an output path is one of the input files (or, for an output
    folder, holds an input among the ``products`` it replaces)."""
    ins = {}
    for p in inputs:
        if p:
            with contextlib.suppress(OSError):
                ins[Path(p).resolve()] = p
    for out in outputs:
        out = Path(out).resolve()
        if out in ins:
            raise InputError(
                f"{out}: the output would replace the input {ins[out]}; choose another output"
            )
        for src, given in ins.items():
            if out in src.parents:
                rel = src.relative_to(out)
                if any(rel.match(pat) or Path(rel.parts[0]).match(pat) for pat in products.names):
                    raise InputError(
                        f"{given}: this input is a product of the output folder {out}, "
                        "which the job replaces; copy it elsewhere or choose another -o"
                    )


def _check_folder(path: Path):
    """``path`` is a folder, or can be created as one."""
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path}: exists and is not a folder")
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputExistsError(f"{path}: cannot be created ({parent} is not a folder)")
            break


def _names(paths, n=5) -> str:
    names = sorted(p.name for p in paths)
    return ", ".join(names[:n]) + (f" and {len(names) - n} more" if len(names) > n else "")


def _check_contents(path: Path, products: Products, *, overwrite: bool, resume: bool, inputs=()):
    """The policy on what ``path`` (an existing folder) holds; raises
    :class:`OutputExistsError` naming the files in the way."""
    # another job starting here at the same moment may have its lock or its probe in the
    # folder: not a file of the user's (it then finds the folder locked and gives up)
    others = [
        p for p in path.iterdir() if p.name != LOCK_NAME and not p.name.startswith(PROBE_PREFIX)
    ]
    if not others:
        return
    if products.continues and is_stereodem_output(path, products.markers):
        return  # a previous run of the command, continued in place
    present = set(_product_paths(path, keep_tiles=False, names=products.names))
    if not (overwrite or resume) and present and is_unfinished_run(path, products, inputs):
        # what a run of this job left when it did not finish: replaced by the rerun; anything
        # else in the folder is the user's, under the rule below
        others = [p for p in others if p not in present]
        if not others:
            return
        raise OutputExistsError.needs_overwrite(
            f"{path}: folder is not empty (it holds {_names(others, 3)}, beside an unfinished "
            "run's products)",
            "to write the products beside its files",
        )
    if not (overwrite or resume):
        if present:
            first, *rest = sorted(present)
            also = f" (as do {_names(rest)})" if rest else ""
            raise OutputExistsError.needs_overwrite(
                f"{first}: exists{also}", "to replace the products of a previous run"
            )
        raise OutputExistsError.needs_overwrite(
            f"{path}: folder exists and is not empty (it holds {_names(others, 3)})",
            "to write the products beside its files",
        )
    if present and not is_stereodem_output(path, products.markers):
        # a folder of the user's (e.g. the one holding the inputs): the products go beside
        # the user's files as long as none of them has a product's name
        raise OutputExistsError(
            f"{path}: not a stereodem output (no {' or '.join(products.markers)} written by "
            f"stereodem) and it "
            f"holds {_names(present)}, which the job would replace; refusing to touch them: "
            "move them or choose an empty or new folder"
        )


def check_output_folder(
    path, products: Products = JOB, *, overwrite: bool = False, resume: bool = False, inputs=()
) -> Path:
    """The one overwrite policy of an output folder, checked before any work; creates and
    changes nothing (:func:`output_folder` checks it again under the lock).

    ``path`` must be a folder or creatable; no input may be among the ``products`` it would
    hold, even with ``overwrite`` (:class:`InputError`); without ``overwrite`` (or ``resume``)
    a non-empty folder is refused, naming its products (or files); with ``overwrite`` a folder
    that holds a product's name must be a previous run's output (one of ``products.markers``):
    a file of the user's is never replaced. Raises :class:`OutputExistsError` naming the
    folder and its files in the way.
    """
    from stereodem.core.raster import check_creatable

    path = Path(path)
    _check_folder(path)
    check_not_an_input([path], inputs, products)
    check_creatable(path)
    if path.is_dir():
        _check_contents(path, products, overwrite=overwrite, resume=resume, inputs=inputs)
    return path


@contextlib.contextmanager
def output_folder(
    path,
    products: Products = JOB,
    *,
    overwrite: bool = False,
    resume: bool = False,
    inputs=(),
):
    """The output folder of a job, created if needed, locked for the job's duration; the
    policy of :func:`check_output_folder` is checked under the lock.

    Parameters
    ----------
    products : Products
        What the job writes into the folder (default: a stereodem job's, :data:`JOB`).
    overwrite : bool
        Replace the products of a previous run: they are set aside
        (:func:`set_aside_products`), deleted when the job succeeds and put back when it
        stops before writing any of its own (a failed rerun leaves the previous products as
        they were); in a non-empty folder that is not a stereodem output, write beside its
        files only when none has a product's name.
    resume : bool
        Continue a previous job: keep its tile cache; its other products are set aside and
        replaced the same way (e.g. a resume refused as another job's loses nothing).
        Without ``overwrite`` or ``resume``, what a run of the same job left when it did not
        finish (:func:`is_unfinished_run`) is set aside and replaced the same way.
    inputs : iterable of paths
        The job's input files; none may be among the outputs. A job whose marker records
        them (:func:`job_inputs`) is recognised by them when it is run again.

    Raises
    ------
    OutputExistsError
        Not a folder, cannot be created, not empty (without ``overwrite``/``resume``), or a
        file of the user's has a product's name.
    OutputLockedError
        Another job holds the folder.
    """
    path = Path(path)
    _check_folder(path)
    check_not_an_input([path], inputs, products)
    created = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputExistsError(f"{path}: cannot be created ({exc.strerror})") from None
    probe = None
    try:  # writable? (os.access says yes to root, even in /proc)
        probe = path / f"{PROBE_PREFIX}{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as exc:
        if created:
            with contextlib.suppress(OSError):
                path.rmdir()
        raise OutputExistsError(f"{path}: folder is not writable ({exc.strerror})") from None
    lock = OutputLock(path)
    try:
        lock.acquire()
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                path.rmdir()
        raise
    ok = False
    aside = None
    try:
        _check_contents(path, products, overwrite=overwrite, resume=resume, inputs=inputs)
        previous = is_stereodem_output(path, products.markers)
        if previous and products.continues:
            pass  # continued in place: the job replaces what it recomputes
        elif not (overwrite or resume) and is_unfinished_run(path, products, inputs):
            # a rerun of a job that did not finish: its leftovers set aside as --resume sets
            # a previous job's products aside (put back if the rerun stops before writing)
            aside = set_aside_products(path, products=products, keep_tiles=False)
        elif (overwrite or resume) and previous:
            # kept until the job has written its own: replaced when it succeeds, put back
            # when it stops before (a failed --overwrite rerun, a resume that refuses the
            # tiles); --resume keeps the tile cache in place
            aside = set_aside_products(path, products=products, keep_tiles=resume)
        yield path
        ok = True
    finally:
        if aside is not None:
            if ok:
                shutil.rmtree(aside, ignore_errors=True)
            else:
                restore_products(path, aside, products)
        lock.release()
        if not ok and created:
            with contextlib.suppress(OSError):
                path.rmdir()  # only if the job left nothing in it
