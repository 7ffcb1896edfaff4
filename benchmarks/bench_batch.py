"""Benchmark of ``femreg.batch.run_batch``: wall time in this process (serial, no Dask) and on local Dask clusters
of 1 and 2 worker processes, and the peak memory of each worker.

Two batches:

* ``small``: 8 synthetic recordings (200 x 40 pixels, 3 frames, tracked), where Dask's per-task overhead shows;
* ``paper``: 4 pairs of the paper-size 3D hard-inclusion sequence (``forward.get_sequence("3d", "HI")``, 3750 x 147
  pixels; frame 1 registered to frames 2, 4, 7, 10), one task each.

Cluster start-up (workers spawned, ~3 s here) is timed apart from the batch itself; the first task on each worker
also pays for importing femreg (~3 s on this machine).  Task CPU is the worker process's CPU time (on a shared
machine the honest measure of cost; wall time shows the speed-up only where cores are free).  Peak RSS is per task
(VmHWM reset at the task's start).

    python benchmarks/bench_batch.py [--only small|paper]

Measured 2026-11-29 on the shared 2-core machine, load average 8-10 from other users (no free core for a second
worker), wall / summed task CPU / peak RSS per worker:

    small  in-process  2.0 s / 0.7 s / 267 MiB;  1 worker  5.3 s / 1.1 s / 300 MiB;  2 workers  6.4 s / 1.1 s / 299 MiB
    paper  in-process  9.5 s / 4.4 s / 507 MiB;  1 worker 12.3 s / 5.1 s / 535 MiB;  2 workers 13.2 s / 6.1 s / 539 MiB

(plus 1-2 s cluster start-up; the extra CPU on workers is the first task's imports and compiled-kernel loading,
~0.4 s per worker); every output bitwise identical to the in-process run.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # the serial run with one BLAS thread too, as the workers (before numpy)
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _small(folder: Path):
    from femreg.synthetic import speckle_image, warp_image

    sp = (0.05, 0.2)
    for k in range(8):
        ref = speckle_image((200, 40), sp, np.random.default_rng(k))
        fr = [ref] + [warp_image(ref, sp, (0, 0), lambda p, j=j: np.column_stack(
            [-0.0025 * j * p[:, 0], 0.00075 * j * (p[:, 1] - 4.0)])) for j in (1, 2)]
        np.savez(folder / f"rec{k:02d}.npz", rf=np.stack(fr), spacing=np.array(sp))
    return {"element_size": 3.0}


def _paper(folder: Path):
    import forward

    seq = forward.get_sequence("3d", "HI")
    np.savez(folder / "hi.npz", rf=np.asarray(seq.frames[:10], np.float32), spacing=np.asarray(seq.spacing),
             origin=np.asarray(seq.origin))
    return {"task": "register", "pairs": [[0, 1], [0, 3], [0, 6], [0, 9]]}


def run(name, make):
    from femreg.batch import jobs_from_inputs, open_client, run_batch

    with tempfile.TemporaryDirectory(prefix=f"bench_batch_{name}_") as tmp:
        tmp = Path(tmp)
        (tmp / "in").mkdir()
        settings = make(tmp / "in")
        jobs = jobs_from_inputs([tmp / "in"], settings)
        ref = None
        for workers in (0, 1, 2):
            t0 = time.perf_counter()
            with open_client(workers) as cl:
                t_start = time.perf_counter() - t0
                t1 = time.perf_counter()
                s = run_batch(jobs, tmp / f"out{workers}", client=cl, workers=0, progress=False)
                t_run = time.perf_counter() - t1
            assert s.ok, s.failed
            u = [np.load(p)["u"] for p in sorted((tmp / f"out{workers}").glob("*/*.npz"))]
            same = ref is None or all(np.array_equal(a, b) for a, b in zip(ref, u))
            ref = ref or u
            task_s = sum(r["wall_s"] for r in s.records)
            cpu_s = sum(r["cpu_s"] for r in s.records)
            mem = ", ".join(f"{m:.0f}" for _, m in sorted(s.worker_memory().values()))
            print(f"{name:6s} workers={workers} ({'in-process' if workers == 0 else 'LocalCluster'}): "
                  f"start-up {t_start:5.1f} s, batch {t_run:6.1f} s, task wall {task_s:6.1f} s, "
                  f"task CPU {cpu_s:6.1f} s, {len(s.records)} tasks, peak RSS per worker {mem} MiB, identical to serial: {same}", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=("small", "paper"))
    a = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f} (2 cores, shared)")
    for name, make in (("small", _small), ("paper", _paper)):
        if a.only in (None, name):
            run(name, make)
    print(f"load average after: {os.getloadavg()[0]:.1f}")
