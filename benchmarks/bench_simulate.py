"""Benchmark: simulate one 20-frame RF sequence (3740 x 147 pixels, 30 scatterers/mm^2) and print the time and
peak memory of each stage plus the compression schedule measured from the true strain.

Usage::

    python benchmarks/bench_simulate.py                 # analytic field: rendering cost only (no FE)
    python benchmarks/bench_simulate.py --field fe      # the FE forward model (cached solve) for --model/--inclusion
    python benchmarks/bench_simulate.py --field fe --model plane-strain --threads 2

Peak memory is the process's maximum resident set size (``resource.getrusage``), which includes the FE solve
when ``--field fe`` solves rather than loads from the cache.
"""
import argparse
import os
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", choices=("analytic", "fe"), default="analytic")
    ap.add_argument("--model", default="3d")
    ap.add_argument("--inclusion", default="HI")
    ap.add_argument("--n-frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2, help="BLAS/OpenMP threads (the target machine has 2 cores)")
    args = ap.parse_args(argv)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, str(args.threads))

    import numpy as np

    import forward
    from forward.sequences import AnalyticField, schedule_figures, simulate_sequence

    field = AnalyticField(forward.INCLUSIONS[args.inclusion]) if args.field == "analytic" else None
    t0 = time.perf_counter()
    seq = simulate_sequence(args.model, args.inclusion, n_frames=args.n_frames, seed=args.seed, snr_db=12.0,
                            field=field)
    wall = time.perf_counter() - t0
    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    t = seq.params["timings_s"]
    n_fr = seq.n_frames
    print(f"model {args.model}/{args.inclusion}, field {seq.params['field_source']}, cpus {os.cpu_count()}")
    print(f"frames {seq.frames.shape} float32 ({seq.frames.nbytes / 1e6:.0f} MB), spacing {seq.spacing} mm, "
          f"origin {seq.origin} mm, {seq.params['n_scatterers']} scatterers in box "
          f"{np.round(seq.params['scatterer_box_mm'], 2).tolist()} mm")
    print(f"field solve/load {t['solve']:.2f} s | true-field tables {t['field_tables']:.2f} s | scatterers + "
          f"displacement at scatterers {t['scatterers']:.2f} s")
    print(f"RENDER {n_fr} frames: {t['render']:.2f} s ({t['render'] / n_fr:.3f} s/frame) | total {wall:.2f} s | "
          f"peak RSS {rss_gb:.2f} GB")
    fig = schedule_figures(seq)
    print("schedule (mean -exx over the imaged area, from true_strain): total {total:.3f} %, mean step "
          "{mean_step:.3f} %, max step {max_step:.3f} %, min step {min_step:.3f} %, 1->3 {frames_1_3:.3f} %, "
          "1->7 {frames_1_7:.3f} %, 1->10 {frames_1_10:.3f} %".format(**fig))
    print("cumulative %:", fig["cumulative"])
    ok = t["render"] < 60 and rss_gb < 4
    print("target (20 frames < 60 s, < 4 GB):", "met" if ok else "NOT met")
    return 0


if __name__ == "__main__":
    sys.exit(main())
