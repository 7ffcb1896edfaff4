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
    python benchmarks/bench_track.py --no-compiled        # without the numba loops (femreg._kernels)

The sequence comes from ``forward.get_sequence("3d", "HI", seed=0)`` (cached under $FEMREG_CACHE; the first call
simulates it, several minutes).  Wall times on a shared machine are pessimistic: compare runs made together.

Measured 2026-11-29, shared 2-core machine at a load average of ~12 (so pessimistic), 20 frames, back to back:
15.7 s (0.83 s per increment: operator 0.24 s, Gauss-Newton 0.44 s at 49 ms per iteration, 9 iterations), peak
RSS 590 MB; the code before the compiled image-term loops, the moved-mesh point location and the banded Cholesky
took 58.3 s in the same conditions (3.07 s per increment: operator 1.29 s, 193 ms per iteration, 730 MB).  Frame
0 -> 19 errors unchanged (total strain 14.2 %); nodal u equal to 6e-15 mm.  Without numba (``--no-compiled``)
1.67 s per increment.

Measured 2026-11-29, strategy "auto" (R_P_sigma, hourglass weight 1000 on the increments, the first increment
from the pyramid, later ones from the previous increment): 19 increments in 6.05 s with the machine nearly idle
(load average 1; 6.06 s CPU), 12.1 s at load 6, 22.9 s at load 13-15; 206 Gauss-Newton iterations, 14 ms mean
when idle; frame 0 -> 19 total strain error 14.2 %, no frame flagged.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: Stages printed first when a result reports them; any other per-stage time it reports follows.
STAGES = ("prefilter", "operator", "mesh", "regularizer_setup", "initial", "gauss_newton", "check")


def _stages(results):
    """Names of the scalar stage times reported by the results, known ones first (``total`` excluded)."""
    seen = []
    for r in results:
        seen += [k for k, v in r.timings.items() if isinstance(v, float) and k != "total" and k not in seen]
    return [s for s in STAGES if s in seen] + [s for s in seen if s not in STAGES]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames to track (first N of the sequence)")
    ap.add_argument("--regularizer", default="momentum-stress")
    ap.add_argument("--strategy", default="auto", choices=("auto", "paper"))
    ap.add_argument("--save", help="write every frame's nodal u to this .npz")
    ap.add_argument("--compare", help="print max |u - u_saved| per frame against a --save file")
    ap.add_argument("--no-compiled", action="store_true", help="use the scipy/numpy paths instead of numba's")
    a = ap.parse_args(argv)

    import forward
    import femreg
    from femreg import _kernels
    from femreg.metrics import field_errors

    if a.no_compiled:
        _kernels.set_compiled(False)
    seq = forward.get_sequence("3d", "HI", seed=0)
    frames = seq.frames[: a.frames]
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"3d-HI seed 0: {frames.shape[0]} frames of {frames.shape[1:]} px, spacing {seq.spacing} mm, "
          f"regularizer {a.regularizer}; compiled loops {'on' if _kernels.use_compiled() else 'off (no numba)'}; "
          f"RSS after loading {rss0:.0f} MB", flush=True)
    t0, c0 = time.perf_counter(), time.process_time()
    out = femreg.track(frames, spacing=seq.spacing, origin=seq.origin, regularizer=a.regularizer,
                       strategy=a.strategy)
    total, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    stages = _stages(out)
    print(f"\n{'k':>3} {'total':>6} " + " ".join(f"{s[:10]:>10}" for s in stages) + f" {'nit':>4} {'s/iter':>7}")
    sums = dict.fromkeys(stages, 0.0)
    iters = []
    for k, r in enumerate(out, start=1):
        t = r.timings
        it = t.get("per_iteration", [])
        iters += list(it)
        for s in stages:
            sums[s] += t.get(s, 0.0)
        print(f"{k:3d} {t['total']:6.3f} " + " ".join(f"{t.get(s, 0.0):10.3f}" for s in stages)
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
