"""Benchmark: `fftune fleet` throughput, captures per second with 1 and 2 Dask workers.

A fleet of 8 capture directories (2 made on the Python test double of the drive with
tests/test_host_experiments.py's small configuration, 0.3 V and 0.5 V Coulomb level, each
copied 4 times; 31-32 runs each: detect, quantify, tune) re-analysed as one task graph on
a dask.distributed LocalCluster of 1 and of 2 worker processes (1 thread each). Printed:
wall time of the graph and capture files per second. The figure depends on the cores free
(2 workers need 2 idle cores to approach twice the rate) and on the capture sizes; the
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
        for i in range(1, 4):
            for name in ("a", "b"):
                shutil.copytree(os.path.join(root, "m0", name), os.path.join(root, f"m{i}", name))
        items, _ = fleet.discover([root])
        n_files = sum(len(fleet._capture_files(p)) for _, p in items)
        print(f"fleet: {len(items)} capture directories, {n_files} capture files")
        for workers in (1, 2):
            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                              dashboard_address=None, host="127.0.0.1") as cluster:
                fleet.run_graph(items[:1], scheduler=cluster.scheduler_address)   # warm the workers
                t0 = time.monotonic()
                rows = fleet.run_graph(items, scheduler=cluster.scheduler_address)
                dt = time.monotonic() - t0
            ok = sum(r["status"] == "ok" for r in rows)
            print(f"  {workers} worker(s): {dt:.2f} s, {n_files / dt:.1f} captures/s, "
                  f"{len(items) / dt:.2f} directories/s ({ok}/{len(rows)} rows ok)")


if __name__ == "__main__":
    main()
