"""Many scenes on a Slurm (or PBS) cluster through dask-jobqueue: one Dask worker per node
slot, one scene per task, the status table in OUT/batch.json.

    pip install dask-jobqueue          # not a stereodem dependency: the cluster side only
    python examples/batch_slurm.py scenes.txt -o /scratch/out --jobs 8 --cores 16
    python examples/batch_slurm.py scenes.txt -o /scratch/out --pbs    # PBSCluster instead

Each Slurm job is one node allocation running ``--cores`` single-threaded Dask workers (one
scene at a time each; stereodem pins every worker's BLAS/OpenCV/GDAL threads to its share of
the node). Run it again after an interruption: finished scenes are skipped, failed ones rerun.
The same as ``stereodem batch scenes.txt -o OUT --dask tcp://scheduler:8786`` against a
scheduler started by hand.
"""

from __future__ import annotations

import argparse
import sys

from stereodem.batch import expand_inputs, run_batch, summary_lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+", help="configurations, granules or list files")
    p.add_argument("-o", "--out", required=True)
    p.add_argument("--template", help="configuration for granules")
    p.add_argument("--jobs", type=int, default=4, help="node allocations (Slurm/PBS jobs)")
    p.add_argument("--cores", type=int, default=16, help="cores per job = scenes at once per job")
    p.add_argument(
        "--memory", default="64GB", help="memory per job (a full granule: ~1.5 GB/scene)"
    )
    p.add_argument("--walltime", default="04:00:00")
    p.add_argument("--queue", help="partition / queue")
    p.add_argument("--pbs", action="store_true", help="PBS instead of Slurm")
    a = p.parse_args(argv)

    from dask.distributed import Client
    from dask_jobqueue import PBSCluster, SLURMCluster

    Cluster = PBSCluster if a.pbs else SLURMCluster
    cluster = Cluster(
        cores=a.cores,
        processes=a.cores,
        memory=a.memory,
        walltime=a.walltime,
        queue=a.queue,
        job_name="stereodem",
    )
    cluster.scale(jobs=a.jobs)
    print(cluster.job_script())
    with Client(cluster) as client:
        result = run_batch(expand_inputs(a.scenes, a.template), a.out, dask=client)
    cluster.close()
    for line in summary_lines(result):
        print(line)
    return 1 if result["this_run"]["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
