"""Adaptive refinement on convex and sector pairs: ``refine="auto"`` against off (``refine=None``), total strain
error (femreg.metrics.field_errors, over the physical mesh) and CPU time per registration, on the pairs of
bench_convex.py (uniform compression 1 / 2 % at radii 40 / 50 / 60 mm and 0.3 / 0.45 / 0.6 deg per line, seeds 0 and
1; sector pairs; the stiff inclusion) and on a held-out set drawn before any choice (other seeds, radii, depths,
the 3 MHz probe, soft inclusions, bending, sector inclusions).

    python benchmarks/convex_refine.py [--set bench|heldout|all] [--quick] [--out FILE.md]

CPU time is ``time.process_time`` (run with OMP_NUM_THREADS=1); one warm-up registration is discarded.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import femreg
from femreg.metrics import field_errors
from forward import fields as F
from forward.beam import make_beam_pair

INC = F.Inclusion("stiff", "plane-strain", 0.01)


def bench_cases(quick=False):
    """(name, field, geometry, make_beam_pair keywords) of bench_convex.py (the linear pairs left out)."""
    out = []
    cases = [(r, p) for r in (40, 50, 60) for p in (0.3, 0.45, 0.6)]
    levels, seeds = (0.01, 0.02), (0, 1)
    if quick:
        cases, levels, seeds = [(50, 0.45), (60, 0.6)], (0.01,), (0,)
    for radius, pitch in cases:
        for level in levels:
            for seed in seeds:
                out.append((f"convex R{radius} {pitch} deg, compression {100 * level:g} %, seed {seed}",
                            F.compression(level), femreg.Convex(radius, pitch), dict(seed=seed)))
    for pitch in (0.3, 0.45, 0.6) if not quick else (0.45,):
        for level in levels:
            out.append((f"sector {pitch} deg from 10 mm, compression {100 * level:g} %", F.compression(level),
                        femreg.Sector(angle_pitch_deg=pitch), dict(seed=0, top_mm=10.0)))
    for radius, pitch in [(40, 0.3), (50, 0.45), (60, 0.6)] if not quick else [(60, 0.6)]:
        for seed in seeds:
            out.append((f"convex R{radius} {pitch} deg, stiff inclusion 1 %, seed {seed}", INC,
                        femreg.Convex(radius, pitch), dict(seed=seed)))
    return out


def heldout_cases():
    """Drawn before any result of refinement on convex frames was seen (seeds 2-11)."""
    C, S = femreg.Convex, femreg.Sector
    soft = F.Inclusion("soft", "plane-strain", 0.01)
    return [
        ("convex R50 0.45 deg, 3 MHz probe, stiff inclusion 1 %, seed 2", INC, C(50, 0.45), dict(seed=2, probe="L3")),
        ("convex R60 0.3 deg, stiff inclusion r 3 mm, seed 3", F.Inclusion("stiff", "plane-strain", 0.01, radius_mm=3.0),
         C(60, 0.3), dict(seed=3)),
        ("convex R40 0.45 deg, soft inclusion 1 %, seed 4", soft, C(40, 0.45), dict(seed=4)),
        ("convex R50 0.6 deg, soft plane-stress inclusion 2 %, 10-40 mm, seed 5",
         F.Inclusion("soft", "plane-stress", 0.02), C(50, 0.6), dict(seed=5, top_mm=10.0, depth_mm=30.0)),
        ("convex R60 0.45 deg, stiff inclusion r 7 mm, 8-48 mm, seed 6",
         F.Inclusion("stiff", "plane-strain", 0.01, radius_mm=7.0), C(60, 0.45), dict(seed=6, top_mm=8.0)),
        ("convex R50 0.3 deg, bending 0.2-2 %, seed 7", F.Bending(0.002, 0.02, 40.0), C(50, 0.3), dict(seed=7)),
        ("convex R40 0.6 deg, 3 MHz probe, bending 0.2-2 %, seed 8", F.Bending(0.002, 0.02, 40.0), C(40, 0.6),
         dict(seed=8, probe="L3")),
        ("sector 0.45 deg from 10 mm, stiff inclusion 1 %, seed 9", INC, S(angle_pitch_deg=0.45),
         dict(seed=9, top_mm=10.0)),
        ("sector 0.3 deg from 10 mm, soft inclusion 1 %, seed 10", soft, S(angle_pitch_deg=0.3),
         dict(seed=10, top_mm=10.0)),
        ("convex R50 0.45 deg, stiff plane-stress inclusion 2 %, seed 11", F.Inclusion("stiff", "plane-stress", 0.02),
         C(50, 0.45), dict(seed=11)),
    ]


def register(pair, geometry, refine):
    t = time.process_time()
    res = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, geometry=geometry,
                          refine=refine)
    return res, field_errors(res, pair.true_displacement, pair.true_strain)["e"], time.process_time() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", choices=("bench", "heldout", "all"), default="all")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", help="also write the table (markdown) here")
    a = ap.parse_args(argv)
    cases = (bench_cases(a.quick) if a.set in ("bench", "all") else []) + (
        heldout_cases() if a.set in ("heldout", "all") else [])
    rows, warm = [], False
    for name, field, geo, kw in cases:
        kw = dict(kw)
        n_rays = int(round(32 / geo.angle_pitch_deg))
        pair = make_beam_pair(field, geo, depth_mm=kw.pop("depth_mm", 40.0), n_rays=n_rays, **kw)
        if not warm:
            register(pair, geo, "auto")
            warm = True
        r0, e0, t0 = register(pair, geo, None)
        r1, e1, t1 = register(pair, geo, "auto")
        rec = getattr(r1, "refinement", None)
        summ = "dropped" if "refinement dropped" in r1.message else (
            "-" if rec is None else f"{r0.mesh.t.shape[1]} -> {r1.mesh.t.shape[1]}")
        rows.append((name, e0, e1, t0, t1, r0.success, r1.success, summ))
        print(f"{name}: {100 * e0:.2f} -> {100 * e1:.2f} % ({100 * (e1 - e0):+.2f}), CPU {t0:.2f} -> {t1:.2f} s "
              f"({t1 / t0:.2f}x), success {r0.success}/{r1.success}, elements {summ}", flush=True)
    lines = ["| case | off | refine=\"auto\" | change | CPU ratio | elements |", "|---|---|---|---|---|---|"]
    lines += [f"| {n} | {100 * e0:.2f} % | {100 * e1:.2f} % | {100 * (e1 - e0):+.2f} | {t1 / t0:.2f} | {s} |"
              + ("" if (ok0 and ok1) else f" success {ok0}/{ok1} |")
              for n, e0, e1, t0, t1, ok0, ok1, s in rows]
    d = np.array([r[2] - r[1] for r in rows])
    q = np.array([r[4] / r[3] for r in rows])
    summary = (f"\n{len(rows)} pairs: change {100 * d.min():+.2f} to {100 * d.max():+.2f} points (median "
               f"{100 * np.median(d):+.2f}); CPU ratio median {np.median(q):.2f}, max {q.max():.2f}")
    print("\n" + "\n".join(lines) + summary)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write("\n".join(lines) + summary + "\n")


if __name__ == "__main__":
    main()
