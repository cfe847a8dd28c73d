"""Benchmark: `fftune fleet` throughput, captures per second with 1 and 2 Dask workers.

A fleet of 16 capture directories (2 made on the Python test double of the drive with
tests/test_host_experiments.py's small configuration, 0.3 V and 0.5 V Coulomb level, each
copied 8 times; 31-32 runs each: detect, quantify, tune) re-analysed as one task graph (the
items batched, a few per worker: fleet.batches) on Dask's local multiprocessing scheduler
with 1 and 2 processes, and on a dask.distributed LocalCluster of 1 and 2 worker processes
(1 thread each). Printed: wall time of the graph and capture files per second. The figure
depends on the cores free (2 workers need 2 idle cores to approach twice the rate) and on
the capture sizes; the local scheduler's figure includes its process pool's start, the
cluster's start-up is not counted.
"""
import os
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.join(REPO, "tests"))

from fftune.host import fleet  # noqa: E402
from fftune.host.pipeline import run_pipeline  # noqa: E402
from host_fixtures import FakeDriveForTests  # noqa: E402
from test_host_experiments import _cfg  # noqa: E402


def main():
    from distributed import LocalCluster

    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as root:
        for name, fc in (("a", 0.3), ("b", 0.5)):
            d = FakeDriveForTests(fc_volt=fc, fv_volt=0.02, noise_std=1e-5)
            d.enable()
            run_pipeline(d, _cfg(), os.path.join(root, "m0", name), log=lambda s: None, figures=False)
        for i in range(1, 8):
            for name in ("a", "b"):
                shutil.copytree(os.path.join(root, "m0", name), os.path.join(root, f"m{i}", name))
        items, _ = fleet.discover([root])
        n_files = sum(len(fleet._capture_files(p)) for _, p in items)
        print(f"fleet: {len(items)} capture directories, {n_files} capture files; load average "
              f"{' '.join(open('/proc/loadavg').read().split()[:3])} on {os.cpu_count()} cores")

        def report(what, dt, rows):
            ok = sum(r["status"] == "ok" for r in rows)
            print(f"  {what}: {dt:.2f} s, {n_files / dt:.1f} captures/s ({ok}/{len(rows)} rows ok)")
        for workers in (1, 2):
            t0 = time.monotonic()
            rows = fleet.run_graph(items, workers=workers)
            report(f"local processes, {workers} worker(s)", time.monotonic() - t0, rows)
        for workers in (1, 2):
            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                              dashboard_address=None, host="127.0.0.1") as cluster:
                fleet.run_graph(items[:workers], scheduler=cluster.scheduler_address)   # warm the workers
                t0 = time.monotonic()
                rows = fleet.run_graph(items, scheduler=cluster.scheduler_address)
                report(f"distributed LocalCluster, {workers} worker(s)", time.monotonic() - t0, rows)


if __name__ == "__main__":
    main()
