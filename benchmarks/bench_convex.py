"""Convex and sector pairs (forward.beam) registered with ``femreg.register(..., geometry=...)``: total strain
error (femreg.metrics.field_errors, over the physical mesh) of uniform compression for radii 40-60 mm and 0.3-0.6
degrees per line, a sector pair, and a stiff inclusion against the linear-array pair of the same field.

    python benchmarks/bench_convex.py [--quick]
"""
from __future__ import annotations

import sys
import time

import femreg
from femreg.metrics import field_errors
from forward import fields as F
from forward.beam import make_beam_pair
from forward.pairs import make_pair


def run(pair, geometry=None):
    t = time.perf_counter()
    kw = {} if geometry is None else dict(geometry=geometry)
    res = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, **kw)
    err = field_errors(res, pair.true_displacement, pair.true_strain)
    return res, err, time.perf_counter() - t


def main(quick=False):
    rows = []
    cases = [(40, 0.3), (50, 0.5), (60, 0.6)] if not quick else [(50, 0.5)]
    for radius, pitch in cases:
        n_rays = int(round(32 / pitch))          # about a 32 degree field of view
        for seed in (0, 1):
            geo = femreg.Convex(radius, pitch)
            p = make_beam_pair(F.compression(0.01), geo, depth_mm=40, n_rays=n_rays, seed=seed)
            res, err, dt = run(p, geo)
            rows.append((f"convex R{radius} {pitch} deg, compression 1 %, seed {seed}", err["e"], res.success, dt))
            print(rows[-1], flush=True)
    geo = femreg.Sector(angle_pitch_deg=0.5)
    p = make_beam_pair(F.compression(0.01), geo, depth_mm=40, n_rays=64, seed=0, top_mm=10.0)
    res, err, dt = run(p, geo)
    rows.append(("sector 0.5 deg, compression 1 %, from 10 mm", err["e"], res.success, dt))
    print(rows[-1], flush=True)
    inc = F.Inclusion("stiff", "plane-strain", 0.01)
    for seed in (0, 1) if not quick else (0,):
        geo = femreg.Convex(50, 0.5)
        p = make_beam_pair(inc, geo, depth_mm=40, n_rays=64, seed=seed)
        res, err, dt = run(p, geo)
        rows.append((f"convex R50 0.5 deg, stiff inclusion 1 %, seed {seed}", err["e"], res.success, dt))
        print(rows[-1], flush=True)
        q = make_pair(inc, "paper", size_mm=(40.0, 30.0), seed=seed, top_mm=3.0)
        res, err, dt = run(q)
        rows.append((f"linear paper probe 40 x 30 mm, stiff inclusion 1 %, seed {seed}", err["e"], res.success, dt))
        print(rows[-1], flush=True)
    print("\n| case | total strain error | success | s |\n|---|---|---|---|")
    for name, e, ok, dt in rows:
        print(f"| {name} | {100 * e:.2f} % | {ok} | {dt:.1f} |")


if __name__ == "__main__":
    main("--quick" in sys.argv)
