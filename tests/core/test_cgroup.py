"""Control-group limits: the CPU quota caps "all cores" (the default --workers) and the memory
limit caps the memory checks, from cgroup v2 and v1 trees laid out as the kernel does (the
host's view, with the process's group below the mount, and a container's, at its root)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from stereodem.core import cgroup, memory, threads
from stereodem.core.errors import InputError

GB = 1 << 30


def _tree(root, proc_cgroup, files):
    """A fake ``/sys/fs/cgroup`` under ``root`` and its ``/proc/self/cgroup``."""
    fs = root / "sys_fs_cgroup"
    fs.mkdir()
    for rel, text in files.items():
        p = fs / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    proc = root / "proc_self_cgroup"
    proc.write_text(proc_cgroup)
    return fs, proc


@pytest.fixture
def fake(tmp_path, monkeypatch):
    def make(proc_cgroup, files):
        fs, proc = _tree(tmp_path, proc_cgroup, files)
        monkeypatch.setattr(cgroup, "CGROUP_FS", fs)
        monkeypatch.setattr(cgroup, "PROC_SELF_CGROUP", proc)

    return make


@pytest.fixture
def eight_cores(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)


def test_v2_quota_of_a_container_caps_the_cores(fake, eight_cores):
    """Docker ``--cpus 1.5`` on cgroup v2 with its own namespace: ``0::/`` and ``cpu.max`` at
    the mount's root; 1.5 cores round up to 2 workers."""
    fake("0::/\n", {"cgroup.controllers": "cpu memory", "cpu.max": "150000 100000\n"})
    assert cgroup.cpu_quota() == pytest.approx(1.5)
    assert threads.cores() == 2
    assert threads.pool_size(None) == 2 and threads.job_threads(None) == 2
    assert threads.pool_size(6) == 6  # an explicit --workers is still obeyed


def test_v2_host_view_takes_the_tightest_limit_along_the_ancestors(fake, eight_cores):
    """Seen from the host, the process's group lies below the mount; a parent's quota (a
    Kubernetes pod) applies to its containers too."""
    fake(
        "0::/kubepods/pod1/ctr\n",
        {
            "cgroup.controllers": "cpu memory",
            "cpu.max": "max 100000",
            "kubepods/pod1/cpu.max": "300000 100000",
            "kubepods/pod1/ctr/cpu.max": "max 100000",
            "kubepods/pod1/ctr/memory.max": "max",
            "kubepods/pod1/memory.max": str(4 * GB),
            "kubepods/pod1/memory.current": str(3 * GB),
            "kubepods/pod1/memory.stat": f"anon 123\ninactive_file {GB}\nactive_file 5\n",
        },
    )
    assert cgroup.cpu_quota() == pytest.approx(3.0) and threads.cores() == 3
    assert cgroup.memory_limit() == 4 * GB
    # limit - (usage - inactive file cache): 4 - (3 - 1) GB
    assert cgroup.memory_available() == 2 * GB


def test_v1_quota_and_memory_limit(fake, eight_cores):
    """cgroup v1 (hybrid hosts, older Docker): ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` in
    the ``cpu,cpuacct`` mount, ``memory.limit_in_bytes`` less the working set; a group's path
    not present under the mount (a container's view) reads the mount's root."""
    fake(
        "12:memory:/docker/abc\n4:cpu,cpuacct:/docker/abc\n0::/\n",
        {
            "cpu,cpuacct/cpu.cfs_quota_us": "400000\n",
            "cpu,cpuacct/cpu.cfs_period_us": "100000\n",
            "memory/memory.limit_in_bytes": str(8 * GB),
            "memory/memory.usage_in_bytes": str(5 * GB),
            "memory/memory.stat": f"cache 1\ntotal_inactive_file {2 * GB}\n",
        },
    )
    assert cgroup.cpu_quota() == pytest.approx(4.0) and threads.cores() == 4
    assert cgroup.memory_limit() == 8 * GB and cgroup.memory_available() == 5 * GB


def test_no_limits_leave_the_affinity_and_the_system_memory(fake, eight_cores):
    """No quota (``max``, ``-1``, v1's page-aligned 2**63 "unlimited") is no cap."""
    fake(
        "4:memory:/x\n3:cpu:/\n0::/\n",
        {
            "cgroup.controllers": "cpu memory",
            "cpu.max": "max 100000\n",
            "memory.max": "max\n",
            "cpu/cpu.cfs_quota_us": "-1\n",
            "cpu/cpu.cfs_period_us": "100000\n",
            "memory/x/memory.limit_in_bytes": "9223372036854771712\n",
        },
    )
    assert cgroup.cpu_quota() is None and cgroup.memory_available() is None
    assert threads.cores() == 8


@pytest.mark.parametrize(
    "files",
    [
        {"cgroup.controllers": "", "cpu.max": "banana", "memory.max": "-5"},
        {"cgroup.controllers": "", "cpu.max": "0 100000", "memory.max": ""},
        {"cgroup.controllers": "", "cpu.max": "100000 0 7"},
        {"cgroup.controllers": "", "cpu.max": "\xff\xfe"},
        {},  # nothing mounted
    ],
)
def test_malformed_or_missing_files_are_no_limit(fake, eight_cores, files):
    fake("0::/\ngarbage line\n", files)
    assert cgroup.cpu_quota() is None and cgroup.memory_available() is None
    assert threads.cores() == 8


def test_a_missing_proc_file_is_no_limit(tmp_path, monkeypatch, eight_cores):
    monkeypatch.setattr(cgroup, "PROC_SELF_CGROUP", tmp_path / "absent")
    assert cgroup.cpu_quota() is None and threads.cores() == 8


def test_a_quota_below_one_core_still_gives_one(fake, eight_cores):
    fake("0::/\n", {"cgroup.controllers": "cpu", "cpu.max": "20000 100000"})
    assert cgroup.cpu_quota() == pytest.approx(0.2) and threads.cores() == 1


def test_the_memory_check_refuses_beyond_the_groups_limit(fake, monkeypatch):
    """An allocation the host could give but the container cannot is refused at once, with a
    message naming it, instead of the group's OOM killer later."""
    monkeypatch.setattr(memory, "_system_available_bytes", lambda: 200 * GB)
    fake("0::/\n", {"cgroup.controllers": "memory", "memory.max": str(2 * GB)})
    assert memory.available_bytes() == 2 * GB
    memory.check_allocation(GB, "a small grid")
    with pytest.raises(InputError, match=r"a 10 GB grid needs 10\.7 GB .* than the 1\.72 GB"):
        memory.check_allocation(10 * GB, "a 10 GB grid")


def test_this_machine_reads_without_error():
    """Whatever this machine has: numbers or None, never an exception."""
    q, m, a = cgroup.cpu_quota(), cgroup.memory_limit(), cgroup.memory_available()
    assert q is None or q > 0
    assert m is None or m > 0
    assert a is None or 0 <= a <= m
    assert 1 <= threads.cores() <= (os.cpu_count() or 1)


def _real_group(tmp_name):
    """A real control group limiting CPU to half a core and memory to 1 GiB, as
    ``(procs files, folders)``: cgroup v1 (``cpu`` and ``memory`` mounts) or v2 (a child of
    the root with both controllers), where this process may create one (root); else skip."""
    fs = Path("/sys/fs/cgroup")
    made = []
    try:
        if (fs / "cpu" / "cpu.cfs_quota_us").is_file() and (fs / "memory").is_dir():
            cpu, mem = fs / "cpu" / tmp_name, fs / "memory" / tmp_name
            for d in (cpu, mem):
                d.mkdir()
                made.append(d)
            (cpu / "cpu.cfs_quota_us").write_text("50000")
            (cpu / "cpu.cfs_period_us").write_text("100000")
            (mem / "memory.limit_in_bytes").write_text(str(GB))
            return [cpu / "cgroup.procs", mem / "cgroup.procs"], made
        if {"cpu", "memory"} <= set((fs / "cgroup.subtree_control").read_text().split()):
            g = fs / tmp_name
            g.mkdir()
            made.append(g)
            (g / "cpu.max").write_text("50000 100000")
            (g / "memory.max").write_text(str(GB))
            return [g / "cgroup.procs"], made
    except OSError as exc:
        for d in reversed(made):
            d.rmdir()
        pytest.skip(f"no control group can be made here ({exc})")
    pytest.skip("no cgroup v1 cpu/memory mounts nor a v2 root with both controllers")


@pytest.mark.skipif(sys.platform != "linux", reason="control groups are Linux's")
def test_a_real_control_group_caps_the_cores_and_the_memory_checks():
    """In a real group of half a core and 1 GiB (made where this runs as root, as in a
    container or a batch job), a process counts 1 core and refuses a 2 GiB allocation at once;
    the same checks outside it see the machine."""
    procs, made = _real_group(f"stereodem_test_{os.getpid()}")
    code = (
        "import sys\n"
        "from stereodem.core import memory, threads\n"
        "from stereodem.core.errors import InputError\n"
        "try:\n"
        "    memory.check_allocation(2 * 2**30, 'a 2 GiB grid')\n"
        "    refused = ''\n"
        "except InputError as e:\n"
        "    refused = str(e)\n"
        "print(threads.cores(), memory.available_bytes() <= 2**30, refused, sep='|')\n"
    )
    enter = "; ".join(f"echo $$ > {p}" for p in procs)
    try:
        r = subprocess.run(
            ["sh", "-c", f'{enter}; exec "$0" -c "$1"', sys.executable, code],
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        for d in reversed(made):
            d.rmdir()
    assert r.returncode == 0, r.stderr
    cores, within, refused = r.stdout.strip().split("|")
    assert cores == "1" and within == "True", r.stdout
    assert re.search(
        r"a 2 GiB grid needs 2\.15 GB of memory, more than the \d+ MB available", refused
    )
