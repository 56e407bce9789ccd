"""Tutorial "A study on a Dask cluster": the horizon study on the pendulum (12 trials) on a Dask cluster, here a
LocalCluster of 2 single-threaded worker processes started by this script; on real machines start the scheduler
and workers with ``dask scheduler`` / ``dask worker`` (or ``dask ssh``, dask-jobqueue) and pass its address.
``python dask_study.py [OUT_DIR] [tcp://SCHEDULER:PORT]`` (pip install "ocpkit[dask]")."""

import sys

from distributed import LocalCluster

from ocpkit import studies
from ocpkit.runs.study import cluster_summary, run

if __name__ == "__main__":  # Dask's worker processes import this file: only the main process starts the cluster
    out = sys.argv[1] if len(sys.argv) > 1 else "results/horizon_dask"
    cluster = None if len(sys.argv) > 2 else LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None)
    scheduler = sys.argv[2] if cluster is None else cluster.scheduler_address
    horizon = studies.get("horizon")
    df = run(horizon.study("quick", problems=["pendulum"]), out, scheduler=scheduler, progress=False)
    print(cluster_summary(df))  # where the trials ran: workers, trials each, seconds
    print(df.pivot_table(index="horizon", values="actual_cost", aggfunc="median"))
    if cluster is not None:
        cluster.close()
