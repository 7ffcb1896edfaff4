"""Throughput of :func:`femreg.elastogram` on simulated freehand loops of 1200 x 128 frames (forward.freehand,
paper probe: 5.5 MHz, 40 MHz sampling, 0.3 mm pitch -> 23 x 38 mm).

Two loops at 30 frames/s:

* ``quarter``: pressing at 2 Hz to 2 %, a pause, the probe sliding: about one pair per four frames is
  registered (default band 0.5-2 %);
* ``every``: pressing at 3 Hz to 3 % with ``max_span=1`` and a band of 0.1-3 %: every consecutive pair whose
  strain is not near a turning point is registered.

Prints input frames per second (frames / wall time of the ``elastogram`` call, simulation and file writing
excluded) and the CPU time per frame (user + system of this process and of its Dask workers: on a machine shared
with other jobs the wall time overstates the cost; the load average is printed).  ``--workers N`` (default 1:
everything in this process): N local Dask worker processes, started once and warmed up (Numba's compilation) by
a first call, as a streaming application keeps them.

Measured (2 cores; load = the 1-minute load average of the machine, other jobs included):

| loop | workers | load | frames/s wall | frames/s of CPU |
|---|---|---|---|---|
| quarter (1 pair in 4.1 frames) | 1 | 1.4 | 42.4 | 39.5 |
| quarter | 2 | 1.1 | 28.7 | 26.0 |
| every (119 of 119 pairs) | 1 | 1.4 | 18.8 | 18.2 |
| every | 2 | 0.7 | 24.1 | 13.7 |
| quarter | 1 | 14.5 | 10.1 | 36.6 |
| every | 1 | 14 | 4.7 | 15.3 |
| quarter / every | 2 | 14.5 | 5.8 / 2.6 | 19.6 / 8.9 |

On a free machine one process meets both targets (>= 25 and >= 10 frames/s); two workers help the every-pair
loop (registration dominates) and not the quarter loop (moving the screening to the workers costs more than it
saves); on a machine loaded 7-fold nothing does, two workers least.

Run: ``python benchmarks/bench_elastogram.py [--frames 120] [--workers 1] [--cache DIR]`` (the loops are cached
as .npz).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from femreg.elastogram import elastogram  # noqa: E402
from forward.freehand import FreehandMotion, FreehandTissue, simulate_freehand  # noqa: E402
from forward.pairs import Probe  # noqa: E402

PROBE = Probe(5.5, 40.0, 0.3, 1.4, name="paper")
SIZE_MM = (1200 * PROBE.spacing[0], 128 * PROBE.spacing[1])
TISSUE = FreehandTissue(inclusion_depth_mm=12.0, inclusion_radius_mm=4.0)
LOOPS = {
    "quarter": (dict(press_hz=2.0, amplitude=0.02, pauses=((0.9, 1.2),), slide_mm_s=1.0, elevation_mm_s=0.5),
                dict()),
    "every": (dict(press_hz=3.0, amplitude=0.03, slide_mm_s=1.0, elevation_mm_s=0.5),
              dict(max_span=1, band=(0.001, 0.03))),
}


def loop(name, n_frames, cache: Path):
    motion_kw, _ = LOOPS[name]
    import hashlib
    key = hashlib.sha1(repr(sorted(motion_kw.items())).encode()).hexdigest()[:8]
    path = cache / f"freehand_{name}_{n_frames}_{key}.npz"
    if path.exists():
        with np.load(path) as z:
            return z["frames"], tuple(z["spacing"]), tuple(z["origin"])
    L = simulate_freehand(FreehandMotion(n_frames=n_frames, **motion_kw), probe=PROBE, size_mm=SIZE_MM,
                          tissue=TISSUE, seed=1, dtype=np.float32)
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, frames=L.frames, spacing=np.array(L.spacing), origin=np.array(L.origin))
    return L.frames, L.spacing, L.origin


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--cache", default=os.environ.get("FEMREG_BENCH_CACHE", "out/bench_elastogram"))
    ap.add_argument("--loops", default="quarter,every")
    a = ap.parse_args(argv)
    cache = Path(a.cache)
    print(f"frames {SIZE_MM[0]:.1f} x {SIZE_MM[1]:.1f} mm, 1200 x 128 samples; {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f} (other jobs share them)")
    with contextlib.ExitStack() as stack:
        client = None
        if a.workers > 1:
            from femreg.batch.engine import open_client
            client = stack.enter_context(open_client(a.workers))
        warm = loop("quarter", 8, cache)
        elastogram(warm[0], spacing=warm[1], origin=warm[2], client=client)      # compiles the numba kernels
        for name in a.loops.split(","):
            frames, spacing, origin = loop(name, a.frames, cache)
            kw = LOOPS[name][1]
            load = os.getloadavg()[0]
            t0, c0, w0 = time.perf_counter(), time.process_time(), _worker_cpu(client)
            res = elastogram(frames, spacing=spacing, origin=origin, client=client, **kw)
            wall = time.perf_counter() - t0
            cpu = time.process_time() - c0 + _worker_cpu(client) - w0
            n_reg = sum(1 for p in res.pairs if p["registered"])
            print(f"{name:8s} {len(frames)} frames, {n_reg} pairs registered (1 per {len(frames) / max(n_reg, 1):.1f} "
                  f"frames), {res.n_usable} usable, {a.workers} worker(s), load {load:.1f}-{os.getloadavg()[0]:.1f}: "
                  f"{len(frames) / wall:6.1f} frames/s wall, {1e3 * cpu / len(frames):6.1f} ms CPU per frame "
                  f"({len(frames) / cpu:.1f} frames/s of CPU); "
                  + ", ".join(f"{k} {v:.2f} s" for k, v in res.timings.items()), flush=True)


def _worker_cpu(client):
    """CPU seconds (user + system) of the Dask workers so far (0 without a client)."""
    if client is None:
        return 0.0
    return float(sum(client.run(time.process_time).values()))

if __name__ == "__main__":
    main()
