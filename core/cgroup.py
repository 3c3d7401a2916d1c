"""What the Linux control groups of this process allow it: CPU time (a quota, in cores) and
memory (a limit, in bytes), from cgroup v2 or v1.

A container (Docker ``--cpus 2 --memory 8g``, a Kubernetes pod's limits) or a batch job
confined by its scheduler (Slurm's ``ConstrainRAMSpace``) still sees the whole host in
``os.sched_getaffinity`` (a CPU quota is no affinity mask) and in ``/proc/meminfo``. A pool
sized by those starts one worker per host core on a quota of two cores, and they are
throttled in turn; an allocation the host could give is killed by the group's OOM killer.

:func:`cpu_quota` and :func:`memory_available` read the limits of the process's own group
and of its ancestors (a limit anywhere above applies too; the tightest wins), where the
group's folder is visible under the mount (a host's view), else at the mount's root (a
container's view of its own group). Files that are missing, unreadable or malformed count as
no limit: these functions never raise. Linux only; elsewhere both return None.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["cpu_quota", "memory_available", "memory_limit"]

#: where the control groups are mounted and where a process's own groups are listed
#: (module attributes: tests point them at a tree of their own)
CGROUP_FS = Path("/sys/fs/cgroup")
PROC_SELF_CGROUP = Path("/proc/self/cgroup")

#: cgroup v1 writes a limit that is no limit as the largest page-aligned int64
_V1_NO_LIMIT = 1 << 62


def _own_groups() -> dict[str, str]:
    """The process's group path per controller of ``/proc/self/cgroup`` (``""`` for the v2
    hierarchy, each controller of a v1 line, e.g. ``"cpu"`` and ``"cpuacct"``, and that
    line's ``"cpu,cpuacct"`` as well: the name of its mount)."""
    try:
        text = PROC_SELF_CGROUP.read_text()
    except (OSError, UnicodeDecodeError):
        return {}
    out = {}
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        out[controllers] = path
        for c in controllers.split(","):
            out.setdefault(c, path)
    return out


def _chain(mount: Path, path: str) -> list[Path]:
    """The group folders whose limits apply: ``mount / path`` and its ancestors up to the
    mount where that folder exists, else the mount alone (a namespaced container)."""
    if not mount.is_dir():
        return []
    own = mount / path.lstrip("/")
    if path.strip("/") and own.is_dir():
        return [own, *[p for p in own.parents if p == mount or mount in p.parents]]
    return [mount]


def _v2_chain(groups: dict[str, str]) -> list[Path]:
    """The v2 group folders of this process (a pure v2 mount, or a hybrid's ``unified``);
    ``groups``: :func:`_own_groups`."""
    if "" not in groups:
        return []
    for mount in (CGROUP_FS, CGROUP_FS / "unified"):
        if (mount / "cgroup.controllers").is_file():
            return _chain(mount, groups[""])
    return []


def _v1_chain(groups: dict[str, str], controller: str) -> list[Path]:
    """The v1 group folders of ``controller`` (``"cpu"``, ``"memory"``) for this process;
    ``groups``: :func:`_own_groups`."""
    if controller not in groups:
        return []
    names = [k for k in groups if controller in k.split(",") and "," in k] + [controller]
    for name in names:
        mount = CGROUP_FS / name
        if mount.is_dir():
            return _chain(mount, groups[controller])
    return []


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _int(text: str | None) -> int | None:
    try:
        return int(text) if text is not None else None
    except ValueError:
        return None


def _stat(path: Path, key: str) -> int:
    """A field of a ``memory.stat`` file (0 where it is missing)."""
    for line in (_read(path) or "").splitlines():
        name, _, value = line.partition(" ")
        if name == key:
            return _int(value) or 0
    return 0


def cpu_quota() -> float | None:
    """The CPU time this process's control groups allow, in cores (``quota / period``: 1.5
    for Docker's ``--cpus 1.5``), the tightest along its groups; None without a quota."""
    groups, quotas = _own_groups(), []
    for folder in _v2_chain(groups):
        fields = (_read(folder / "cpu.max") or "").split()
        if len(fields) == 2 and fields[0] != "max":
            q, p = _int(fields[0]), _int(fields[1])
            if q and p and q > 0 and p > 0:
                quotas.append(q / p)
    for folder in _v1_chain(groups, "cpu"):
        q = _int(_read(folder / "cpu.cfs_quota_us"))
        p = _int(_read(folder / "cpu.cfs_period_us"))
        if q and p and q > 0 and p > 0:
            quotas.append(q / p)
    return min(quotas) if quotas else None


def _memory_groups() -> list[tuple[int, int]]:
    """(limit, working set) in bytes of each group along this process's that has a memory
    limit; the working set is the group's usage less its inactive file cache (what the
    kernel reclaims before the OOM killer acts, as ``docker stats`` and Kubernetes count)."""
    groups, out = _own_groups(), []
    for folder in _v2_chain(groups):
        limit = _int(_read(folder / "memory.max"))  # "max": no limit (None)
        if limit is not None and limit > 0:
            used = _int(_read(folder / "memory.current")) or 0
            out.append((limit, max(used - _stat(folder / "memory.stat", "inactive_file"), 0)))
    for folder in _v1_chain(groups, "memory"):
        limit = _int(_read(folder / "memory.limit_in_bytes"))
        if limit is not None and 0 < limit < _V1_NO_LIMIT:
            used = _int(_read(folder / "memory.usage_in_bytes")) or 0
            stat = folder / "memory.stat"  # total_*: the group's and its descendants'
            inactive = _stat(stat, "total_inactive_file") or _stat(stat, "inactive_file")
            out.append((limit, max(used - inactive, 0)))
    return out


def memory_limit() -> int | None:
    """The memory limit of this process's control groups in bytes (the tightest); None
    without one."""
    groups = _memory_groups()
    return min(limit for limit, _ in groups) if groups else None


def memory_available() -> int | None:
    """Bytes this process's control groups still allow (each limited group's limit less its
    working set, the least of them); None without a memory limit."""
    groups = _memory_groups()
    return min(max(limit - used, 0) for limit, used in groups) if groups else None
