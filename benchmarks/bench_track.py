"""Benchmark of ``femreg.track`` on the paper's 20-frame sequence (3D model, hard inclusion, SNR 12 dB, seed 0;
3740 x 147 pixels, dx 0.01925 mm, dy 0.3 mm), default settings (R_P_sigma, ``grid="current"``, accumulation).

Prints the total time (wall and CPU: on a shared machine the CPU time of this single-threaded process is what an
idle machine's wall time would be), every increment's stages (prefilter, mesh = speckle statistics and mesh,
initial guess, Gauss-Newton including the pixel location, quadrature and regulariser set-up, check = peak-hopping
check and quality map) with the iteration count and mean time per iteration, the peak RSS, and the accumulated
errors of the last frame against the forward model's truth (femreg.metrics).

    python benchmarks/bench_track.py                      # 20 frames
    python benchmarks/bench_track.py --frames 6 --save a.npz
    python benchmarks/bench_track.py --compare a.npz      # max |u - u_saved| per frame (equality checks)

The sequence comes from ``forward.get_sequence("3d", "HI", seed=0)`` (cached under $FEMREG_CACHE; the first call
simulates it, several minutes).  Wall times on a shared machine are pessimistic: compare runs made together.

Measured 2026-11-29 on the shared 2-core machine, strategy "auto" (R_P_sigma, hourglass weight 1000 on the
increments, the first increment from the pyramid, later ones from the previous increment): 19 increments in 12.1 s
wall at load average 6 (22.9 s at load 13-15), 5.9 s CPU; 206 Gauss-Newton iterations, 29 ms mean; frame 0 -> 19
total strain error 14.2 %, no frame flagged.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

STAGES = ("prefilter", "mesh", "initial", "gauss_newton", "check")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames to track (first N of the sequence)")
    ap.add_argument("--regularizer", default="momentum-stress")
    ap.add_argument("--strategy", default="auto", choices=("auto", "paper"))
    ap.add_argument("--save", help="write every frame's nodal u to this .npz")
    ap.add_argument("--compare", help="print max |u - u_saved| per frame against a --save file")
    a = ap.parse_args(argv)

    import forward
    import femreg
    from femreg.metrics import field_errors

    seq = forward.get_sequence("3d", "HI", seed=0)
    frames = seq.frames[: a.frames]
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"3d-HI seed 0: {frames.shape[0]} frames of {frames.shape[1:]} px, spacing {seq.spacing} mm, "
          f"regularizer {a.regularizer}; RSS after loading {rss0:.0f} MB", flush=True)
    t0, c0 = time.perf_counter(), time.process_time()
    out = femreg.track(frames, spacing=seq.spacing, origin=seq.origin, regularizer=a.regularizer,
                       strategy=a.strategy)
    total, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    print(f"\n{'k':>3} {'total':>6} " + " ".join(f"{s[:10]:>10}" for s in STAGES) + f" {'nit':>4} {'s/iter':>7}")
    sums = dict.fromkeys(STAGES, 0.0)
    iters = []
    for k, r in enumerate(out, start=1):
        t = r.timings
        it = t.get("per_iteration", [])
        iters += list(it)
        for s in STAGES:
            sums[s] += t.get(s, 0.0)
        print(f"{k:3d} {t['total']:6.3f} " + " ".join(f"{t.get(s, 0.0):10.3f}" for s in STAGES)
              + f" {r.nit:4d} {np.mean(it) if it else float('nan'):7.4f}")
    n = len(out)
    print(f"\nTOTAL {total:.2f} s wall, {cpu:.2f} s CPU of this process (the wall time on an idle machine with one "
          f"thread), for {n} increments ({total / n:.3f} s per increment); per stage (sum): "
          + ", ".join(f"{s} {v:.2f}" for s, v in sums.items()))
    print(f"Gauss-Newton: {len(iters)} iterations, {np.mean(iters) * 1e3:.1f} ms mean, "
          f"{np.median(iters) * 1e3:.1f} ms median per iteration")
    print(f"peak RSS {peak:.0f} MB")
    k = n
    e = field_errors(out[-1], lambda p: seq.true_displacement(k, p), lambda p: seq.true_strain(k, p))
    print(f"frame 0 -> {k} errors: ux {100 * e['ux']:.2f} %  uy {100 * e['uy']:.1f} %  exx {100 * e['exx']:.1f} %  "
          f"eyy {100 * e['eyy']:.1f} %  exy {100 * e['exy']:.1f} %  total strain {100 * e['e']:.1f} %  "
          f"flags {sum(bool(f) for f in out.flags)}")
    if a.save:
        np.savez(a.save, **{f"frame{k}": r.u for k, r in enumerate(out, start=1)})
    if a.compare:
        with np.load(a.compare) as z:
            d = [float(np.abs(r.u - z[f"frame{k}"]).max()) for k, r in enumerate(out, start=1) if f"frame{k}" in z]
        print("max |u - u_saved| per frame (mm): " + " ".join(f"{v:.1e}" for v in d))


if __name__ == "__main__":
    main()
