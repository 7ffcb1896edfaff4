"""Convex and sector pairs (forward.beam) registered with ``femreg.register(..., geometry=...)``: total strain
error (femreg.metrics.field_errors, over the physical mesh) of uniform compression 1 and 2 % for radii 40 / 50 /
60 mm and 0.3 / 0.45 / 0.6 degrees per line (two seeds), sector pairs, and a stiff inclusion against the
linear-array pair of the same field; 40 mm of range from 3 mm (sector: from 10 mm), about 32 degrees, SNR 30 dB.

    python benchmarks/bench_convex.py [--quick] [--alpha A] [--out FILE.md]

``--alpha``: a fixed alpha for every registration (default: femreg's, with the beam factor
:func:`femreg.geometry.beam_alpha_factor`).
"""
from __future__ import annotations

import argparse
import time

import femreg
from femreg.metrics import field_errors
from forward import fields as F
from forward.beam import make_beam_pair
from forward.pairs import make_pair


def run(pair, geometry=None, alpha=None):
    t = time.perf_counter()
    kw = {} if geometry is None else dict(geometry=geometry)
    res = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, alpha=alpha, **kw)
    err = field_errors(res, pair.true_displacement, pair.true_strain)
    return res, err, time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="R50 / 0.45 deg, R60 / 0.6 deg, 1 %, seed 0 only")
    ap.add_argument("--alpha", type=float)
    ap.add_argument("--out", help="also write the table (markdown) here")
    a = ap.parse_args(argv)
    rows = []

    def add(name, res, err, dt):
        rows.append((name, err["e"], err["eyy"], res.success, res.alpha, dt))
        print(f"{name}: {100 * err['e']:.2f} % (e_yy {100 * err['eyy']:.2f} %), alpha {res.alpha:.3g}, "
              f"{dt:.1f} s", flush=True)

    cases = [(r, p) for r in (40, 50, 60) for p in (0.3, 0.45, 0.6)]
    levels, seeds = (0.01, 0.02), (0, 1)
    if a.quick:
        cases, levels, seeds = [(50, 0.45), (60, 0.6)], (0.01,), (0,)
    for radius, pitch in cases:
        geo = femreg.Convex(radius, pitch)
        for level in levels:
            for seed in seeds:
                p = make_beam_pair(F.compression(level), geo, depth_mm=40, n_rays=int(round(32 / pitch)), seed=seed)
                add(f"convex R{radius} {pitch} deg, compression {100 * level:g} %, seed {seed}", *run(p, geo, a.alpha))
    for pitch in (0.3, 0.45, 0.6) if not a.quick else (0.45,):
        geo = femreg.Sector(angle_pitch_deg=pitch)
        for level in levels:
            p = make_beam_pair(F.compression(level), geo, depth_mm=40, n_rays=int(round(32 / pitch)), seed=0,
                               top_mm=10.0)
            add(f"sector {pitch} deg from 10 mm, compression {100 * level:g} %, seed 0", *run(p, geo, a.alpha))
    inc = F.Inclusion("stiff", "plane-strain", 0.01)
    for seed in seeds:
        q = make_pair(inc, "paper", size_mm=(40.0, 30.0), seed=seed, top_mm=3.0)
        add(f"linear paper probe 40 x 30 mm, stiff inclusion 1 %, seed {seed}", *run(q, None, a.alpha))
    for radius, pitch in [(40, 0.3), (50, 0.45), (60, 0.6)] if not a.quick else [(60, 0.6)]:
        geo = femreg.Convex(radius, pitch)
        for seed in seeds:
            p = make_beam_pair(inc, geo, depth_mm=40, n_rays=int(round(32 / pitch)), seed=seed)
            add(f"convex R{radius} {pitch} deg, stiff inclusion 1 %, seed {seed}", *run(p, geo, a.alpha))
    lines = ["| case | total strain error | e_yy error | success | alpha | s |", "|---|---|---|---|---|---|"]
    lines += [f"| {n} | {100 * e:.2f} % | {100 * ey:.2f} % | {ok} | {al:.3g} | {dt:.1f} |"
              for n, e, ey, ok, al, dt in rows]
    print("\n" + "\n".join(lines))
    if a.out:
        with open(a.out, "w") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
