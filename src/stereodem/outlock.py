"""One job per output folder: an exclusive lock, products replaced only on request, inputs
never among the outputs.

:class:`OutputLock` holds ``OUT/.stereodem.lock`` with ``fcntl.flock`` (exclusive,
non-blocking) for the life of a job. The kernel drops the lock when the process dies, however
it dies, so a lock file left by a killed run (stale) is simply taken over; the file records
the holder's PID and host for the message a second job gets. The lock file is removed on
release.

:func:`output_folder` is what the commands use: it checks the folder, takes the lock, then,
with ``overwrite``, removes the products of the previous job (only in a folder that a
stereodem job wrote, recognised by its ``run.json``, ``dem_report.json`` or tile cache);
on ``resume`` it keeps the tile cache. In a folder of the user's (e.g. the one holding the
inputs) it writes the products beside the user's files only when none of them has a product's
name: nothing of the user's is replaced or removed. If the job fails before writing anything, a
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
import threading
import time
from pathlib import Path

from stereodem.core.errors import InputError, OutputExistsError

log = logging.getLogger(__name__)

__all__ = [
    "LOCK_NAME",
    "OutputLock",
    "OutputLockedError",
    "output_folder",
    "remove_products",
    "remove_products_in_background",
    "is_stereodem_output",
    "check_not_an_input",
    "PRODUCTS",
]

LOCK_NAME = ".stereodem.lock"
#: the writability probe a job starting in the folder leaves there for an instant
PROBE_PREFIX = ".stereodem-probe-"
#: the folder a job moves the previous job's products into, to delete them while it runs
REMOVING_PREFIX = ".stereodem-removing-"

#: what a stereodem job writes into its output folder (files and folders, glob patterns)
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
    # stereodem stack / change
    "stack.json",
    "stack.zarr",
    "rate.tif",
    "rate_sigma.tif",
    "n_obs.tif",
    "n_rejected.tif",
    "volumes.json",
    "change.json",
    "dh.tif",
    "dh_sigma.tif",
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


def is_stereodem_output(folder) -> bool:
    """Whether ``folder`` holds the products of a stereodem job (or what a job killed while it
    deleted them left: :func:`remove_products_in_background`)."""
    folder = Path(folder)
    return any((folder / m).exists() for m in MARKERS) or any(folder.glob(REMOVING_PREFIX + "*"))


def _product_paths(folder: Path, keep_tiles: bool):
    for pattern in PRODUCTS:
        if keep_tiles and pattern == "tiles":
            continue
        yield from folder.glob(pattern)


def remove_products(folder, *, keep_tiles: bool) -> list[str]:
    """Remove the previous job's products from ``folder`` (the tile cache too unless
    ``keep_tiles``); other files are left alone. Returns the names removed."""
    removed, paths = _products_to_remove(Path(folder), keep_tiles)
    for p in paths:
        _delete(p)
    return removed


def remove_products_in_background(folder, *, keep_tiles: bool):
    """:func:`remove_products`, the deletion on a thread: the products are moved into a hidden
    folder of ``folder`` (a rename each: out of the job's way at once) and deleted there while
    the job runs. Returns (the names removed, the deleting thread or None).

    Deleting a previous job's half gigabyte of tiles and rasters took 0.2-0.4 s, mostly in
    the kernel, before any work could start. A job killed meanwhile leaves the hidden folder,
    which the next ``--overwrite`` removes as one of the products (:data:`PRODUCTS`)."""
    folder = Path(folder)
    removed, paths = _products_to_remove(folder, keep_tiles)
    if not paths:
        return removed, None
    trash = folder / f"{REMOVING_PREFIX}{os.getpid()}-{time.monotonic_ns()}"
    try:
        trash.mkdir()
        for p in paths:
            p.rename(trash / p.name)
    except OSError:  # one could not be moved: all are deleted here and now
        for p in (*paths, trash):
            if p.exists() or p.is_symlink():
                _delete(p)
        return removed, None
    thread = threading.Thread(
        target=shutil.rmtree, args=(trash,), kwargs={"ignore_errors": True}, name="stereodem-rm"
    )
    thread.start()
    return removed, thread


def _products_to_remove(folder: Path, keep_tiles: bool):
    paths = sorted(set(_product_paths(folder, keep_tiles)))
    removed = [p.name for p in paths]
    if removed:
        log.info("%s: removed the previous job's %s", folder, ", ".join(removed))
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


def check_not_an_input(outputs, inputs):
    """:class:`InputError` if an output path is one of the input files (or, for an output
    folder, holds an input among the products it replaces)."""
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
                if any(rel.match(pat) or Path(rel.parts[0]).match(pat) for pat in PRODUCTS):
                    raise InputError(
                        f"{given}: this input is a product of the output folder {out}, "
                        "which the job replaces; copy it elsewhere or choose another -o"
                    )


def _check_folder(path: Path, *, overwrite: bool, resume: bool):
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path}: exists and is not a folder")
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputExistsError(f"{path}: cannot be created ({parent} is not a folder)")
            break


@contextlib.contextmanager
def output_folder(
    path, *, overwrite: bool = False, resume: bool = False, inputs=(), background: bool = False
):
    """The output folder of a job, created if needed, locked for the job's duration.

    Parameters
    ----------
    overwrite : bool
        Replace the products of a previous job; in a non-empty folder that is not a stereodem
        output, write beside its files only when none has a product's name (:data:`PRODUCTS`).
    resume : bool
        Continue a previous job: keep its tile cache (its other products are replaced).
    inputs : iterable of paths
        The job's input files; none may be among the outputs.
    background : bool
        Delete the previous job's products on a thread while the job runs (they are moved
        out of its way first: :func:`remove_products_in_background`); the deletion ends
        before the lock is released. For jobs with a core to spare.

    Raises
    ------
    OutputExistsError
        Not a folder, cannot be created, not empty (without ``overwrite``/``resume``).
    OutputLockedError
        Another job holds the folder.
    """
    path = Path(path)
    _check_folder(path, overwrite=overwrite, resume=resume)
    check_not_an_input([path], inputs)
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
    deleting = None
    try:
        # another job starting here at the same moment may have its probe in the folder:
        # not a file of the user's (it then finds the folder locked and gives up)
        others = [
            p for p in path.iterdir() if p.name != LOCK_NAME and not p.name.startswith(PROBE_PREFIX)
        ]
        if others:
            if not (overwrite or resume):
                raise OutputExistsError(
                    f"{path}: folder exists and is not empty; pass --overwrite "
                    "to replace its products (or --resume to continue its job)"
                )
            if is_stereodem_output(path):
                if background:
                    deleting = remove_products_in_background(path, keep_tiles=resume)[1]
                else:
                    remove_products(path, keep_tiles=resume)
            else:
                # a folder of the user's (e.g. the one holding the inputs): the products go
                # beside the user's files as long as none of them has a product's name
                clash = sorted(p.name for p in set(_product_paths(path, keep_tiles=False)))
                if clash:
                    raise OutputExistsError(
                        f"{path}: not a stereodem output (no run.json or "
                        f"dem_report.json) and it holds {', '.join(clash[:5])}, "
                        "which the job would replace; refusing to touch them: "
                        "choose an empty or new folder"
                    )
        yield path
        ok = True
    finally:
        if deleting is not None:
            deleting.join()
        lock.release()
        if not ok and created:
            with contextlib.suppress(OSError):
                path.rmdir()  # only if the job left nothing in it
