"""Convex / sector cine loops: accumulated strain error of ``femreg.track(..., geometry=femreg.Convex(...))``.

A sequence (``forward.beam.make_beam_sequence``: the same scatterers under ``field.at(k * step)``, frame k rendered
along the rays of the geometry) is tracked frame 0 -> k in both modes: ``"accumulate"`` (eq:IR, each increment
registered on frame k-1's samples over the frame-0 physical mesh moved by S_{k-1}) and ``"direct"`` (frame 0 -> k
registered independently).  Score: total strain error (``femreg.metrics.field_errors``, relative L2 of exx, eyy,
exy over the physical mesh) at every frame against the exact frame-0 -> k field; CPU time per frame
(``time.process_time``, one warm-up registration discarded; run with OMP_NUM_THREADS=1).

    python benchmarks/convex_track.py [--frames 6] [--step 0.005] [--cases convex-compression ...] [--seeds 0]
                                      [--alpha auto]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import femreg  # noqa: E402
from femreg.metrics import field_errors  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.beam import make_beam_sequence  # noqa: E402

#: case: (field, geometry, make_beam_sequence keywords)
CASES = {
    "convex-compression": (F.compression(0.01), femreg.Convex(50, 0.5), dict(depth_mm=30.0, n_rays=64)),
    "convex-bending": (F.Bending(0.002, 0.02, 40.0), femreg.Convex(50, 0.5), dict(depth_mm=30.0, n_rays=64)),
    "sector-compression": (F.compression(0.01), femreg.Sector(angle_pitch_deg=0.45),
                           dict(depth_mm=30.0, n_rays=64, top_mm=10.0)),
}


def run(name, seed, args):
    field, geo, kw = CASES[name]
    seq = make_beam_sequence(field, geo, n_frames=args.frames, step=args.step, seed=seed, **kw)
    rows = {}
    for mode in ("accumulate", "direct"):
        t = time.process_time()
        out = femreg.track(seq.frames, spacing=seq.spacing[0], origin=seq.origin, geometry=geo, mode=mode,
                           alpha=args.alpha)
        dt = (time.process_time() - t) / len(out)
        errs = [field_errors(r, lambda p, k=k: seq.true_displacement(k, p),
                             lambda p, k=k: seq.true_strain(k, p))["e"] for k, r in enumerate(out, start=1)]
        rows[mode] = (errs, dt, all(r.success for r in out), min(r.ncc_after for r in out))
    return seq, rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--step", type=float, default=0.005, help="level per frame (fraction)")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--alpha", default=None, help="'auto' (chosen once on the first pair) or a number; default: "
                                                   "the beam's default alpha")
    args = ap.parse_args(argv)
    if args.alpha not in (None, "auto"):
        args.alpha = float(args.alpha)
    # warm-up (compilation), not timed
    w = make_beam_sequence(F.compression(0.01), femreg.Convex(50, 0.5), depth_mm=8.0, n_rays=32, n_frames=2,
                           step=0.005)
    femreg.track(w.frames, spacing=w.spacing[0], origin=w.origin, geometry=femreg.Convex(50, 0.5))
    print(f"{args.frames} frames, {100 * args.step:g} % per frame; total strain error frame 0 -> k, % "
          "(k = 1 .. N-1); CPU s per frame")
    for name in args.cases:
        for seed in args.seeds:
            seq, rows = run(name, seed, args)
            for mode, (errs, dt, ok, ncc) in rows.items():
                print(f"{name:20s} seed {seed} {tuple(seq.frames.shape[1:])} {mode:10s} "
                      + " ".join(f"{100 * e:5.2f}" for e in errs)
                      + f"  | {dt:5.2f} s/frame, all success {ok}, min NCC {ncc:.3f}", flush=True)


if __name__ == "__main__":
    main()
