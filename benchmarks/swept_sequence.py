"""Swept-probe volume sequences: accumulated strain error of ``femreg.track(..., geometry=femreg.Swept(...))``.

A sequence of swept volumes (``forward.swept.make_swept_sequence``: frame 0 and one volume per frame-0 -> frame-k
field, the same scatterers) is tracked with ``femreg.track`` and a swept geometry (every volume scan-converted once
onto the Cartesian grid of frame 0, :func:`femreg.swept.scan_convert_sequence`, then the volume tracking of
:func:`femreg.volume.track_volume`, eq:IR); the same sequence scan-converted by hand (``cartesian_grid`` +
``scan_convert(..., grid=)``) and tracked as Cartesian volumes; frame 0 -> N registered directly
(``femreg.register`` with the geometry); and a Cartesian sequence of the same fields and probe
(``forward.volume.make_volume_sequence``) over the swept result's box.  Fields: per frame an axial compression of
``--step`` (0.75 %) and an x-z shear of ``--shear`` (0.2 %), frame 0 -> k exactly k of each.  Score: total strain
error (relative L2 of the six components, shears counted twice) on a 12^3 lattice over the swept mesh box less
``--margin`` mm, for every frame.

    python benchmarks/swept_sequence.py [--cases small medium] [--seeds 0 1] [--frames 4] [--json rows.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

WEIGHTS = np.array([1, 1, 1, 2, 2, 2.0])

#: case: (geometry keywords, probe, depth mm, top mm, lines, frames, element size mm)
CASES = {
    "small": (dict(sweep_radius_mm=20.0, angle_step_deg=1.0), "matrix7", 8.0, 3.0, 40, 23, 2.0),
    "medium": (dict(sweep_radius_mm=20.0, angle_step_deg=1.0), "matrix7", 14.0, 3.0, 56, 25, 2.0),
}


def strain_error(res, field, lo, hi, n=12):
    P = np.column_stack([g.ravel() for g in np.meshgrid(*[np.linspace(lo[a], hi[a], n) for a in range(3)],
                                                        indexing="ij")])
    d, t = res.strain(P) - field.strain(P), field.strain(P)
    return float(np.sqrt(np.sum(WEIGHTS * d ** 2) / np.sum(WEIGHTS * t ** 2)))


def run(case, seed, args):
    import femreg
    from femreg.swept import cartesian_grid, scan_convert, swept_spacing
    from forward.swept import make_swept_sequence
    from forward.volume import Affine3D, make_volume_sequence

    gkw, probe, depth, top, n_lines, n_frames, h = CASES[case]
    geo = femreg.Swept(**gkw)
    fields = [Affine3D(1.0 - (1.0 - args.step) ** k, shear={"xz": args.shear * k}, centre=(top + depth / 2, 0, 0))
              for k in range(1, args.frames)]
    seq = make_swept_sequence(fields, geo, probe, depth_mm=depth, n_lines=n_lines, n_frames=n_frames, top_mm=top,
                              seed=seed)
    t = time.process_time()
    tr = femreg.track(seq.frames, spacing=seq.spacing, origin=seq.origin, geometry=geo, element_size=h)
    t_swept = time.process_time() - t
    lo, hi = tr.accumulated[0].mesh.p.min(axis=1), tr.accumulated[0].mesh.p.max(axis=1)
    m = args.margin
    row = dict(case=case, seed=seed, frames=args.frames, samples=list(seq.frames.shape[1:]),
               voxels=list(tr.swept.cartesian[0]), flags=tr.flags,
               swept=[strain_error(a, f, lo + m, hi - m) for a, f in zip(tr.accumulated, fields)], cpu_swept=t_swept)
    t = time.process_time()
    sp, org = swept_spacing(seq.spacing, geo, seq.origin)
    grid = cartesian_grid(geo, seq.frames[0], sp, org)
    conv = np.stack([scan_convert(v, geo, sp, org, grid=grid)[0] for v in seq.frames])
    tc = femreg.track(conv, spacing=grid[1], origin=grid[2], element_size=h)
    row["cpu_by_hand"] = time.process_time() - t
    row["by_hand"] = [strain_error(a, f, lo + m, hi - m) for a, f in zip(tc.accumulated, fields)]
    row["max_u_diff_mm"] = float(max(np.max(np.abs(a.u - b.u)) for a, b in zip(tr.accumulated, tc.accumulated)))
    t = time.process_time()
    rd = femreg.register(seq.frames[0], seq.frames[-1], spacing=seq.spacing, origin=seq.origin, geometry=geo,
                         element_size=h)
    row["cpu_direct"] = time.process_time() - t
    row["direct_last"] = strain_error(rd, fields[-1], lo + m, hi - m)
    # Cartesian volumes of the same fields over the swept mesh box + 1 mm
    size = (float(hi[0] - lo[0] + 2.0), 2 * float(max(abs(lo[1]), abs(hi[1]))) + 2.0,
            2 * float(max(abs(lo[2]), abs(hi[2]))) + 2.0)
    cs = make_volume_sequence(fields, probe, size, top_mm=float(lo[0] - 1.0), seed=seed)
    t = time.process_time()
    tcart = femreg.track(cs.frames, spacing=cs.spacing, origin=cs.origin, element_size=h)
    row["cpu_cartesian"] = time.process_time() - t
    row["cartesian"] = [strain_error(a, f, lo + m, hi - m) for a, f in zip(tcart.accumulated, fields)]
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--frames", type=int, default=4, help="volumes in the sequence (frame 0 included)")
    ap.add_argument("--step", type=float, default=0.0075, help="axial compression per frame (fraction)")
    ap.add_argument("--shear", type=float, default=0.002, help="x-z shear per frame")
    ap.add_argument("--margin", type=float, default=1.0, help="mm left out inside the mesh box when scoring")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    rows = []
    for case in args.cases:
        for seed in args.seeds:
            r = run(case, seed, args)
            rows.append(r)
            pct = lambda v: " / ".join(f"{100 * x:.2f}" for x in v)     # noqa: E731
            print(f"{case} seed {seed}: {r['samples']} -> {r['voxels']}; accumulated total strain error per frame "
                  f"swept {pct(r['swept'])} % ({r['cpu_swept']:.0f} s CPU), by hand {pct(r['by_hand'])} % "
                  f"(max |u diff| {r['max_u_diff_mm']:.1e} mm), direct 0->{args.frames - 1} "
                  f"{100 * r['direct_last']:.2f} %, Cartesian volumes {pct(r['cartesian'])} % "
                  f"({r['cpu_cartesian']:.0f} s); flags {r['flags']}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
