"""What the default alpha of a convex frame's physical solve should follow: the line spacing, the beam's width in
lines, or both.  Convex pairs (forward.beam, R50, 40 mm of range from 3 mm, about 32 degrees, SNR 30 dB) whose line
spacing at the middle sample (0.45 / 0.76 / 1.08 mm: 0.35 / 0.6 / 0.85 degrees) and beam width in lines (2 / 3 /
4.5 line spacings, -6 dB at ``rho_c``) vary independently, under 1 % compression and a stiff inclusion (1 %);
each registered with the default alpha's factor ``femreg.geometry.beam_alpha_factor`` replaced by a sweep of
fixed factors (the sample-space start keeps the linear default, as in the default path).  Recorded: the total
strain error (femreg.metrics.field_errors ``e``), the inclusion's strain ratio (e_xx over the ring 1.5-2.5 r
over that within 0.6 r, on the result's samples; the truth's beside it) and the lateral speckle cell of the
reference frame in lines (femreg.geometry.lateral_cell_lines).  Every pair is also registered at the factor of the
line spacing alone (``beam_alpha_factor(ds)``) and at femreg's default (``default_beam_alpha_factor``, which
counts the spacing in RF periods for pulses longer than the paper probe's; docs/geometry.md).

    python benchmarks/convex_alpha_beam.py [--quick] [--seeds 0] [--probe paper|L3|L7] [--pitches P ..]
        [--lpbs B ..] [--level 0.01] [--fields compression inclusion] [--factors F ..] [--json FILE]

The paper probe's axial pulse by default (the probe's own beam width is replaced by ``--lpbs`` line spacings);
``--probe L3`` the 3 MHz one.  1.5-3 s per registration (2 shared cores, OMP_NUM_THREADS=1).  The measured
table: docs/geometry.md, "The probe's pulse and beam width".
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
import femreg  # noqa: E402
import femreg.geometry as G  # noqa: E402
from femreg.metrics import field_errors  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.beam import make_beam_pair  # noqa: E402
from forward.pairs import as_probe  # noqa: E402

FACTORS = (1.0, 3.0, 10.0, 30.0, 100.0, 300.0)


def strain_ratio(res, pair):
    """(estimated, true) background-over-disk ratio of e_xx on the result's registered samples."""
    g = res.on_grid()
    P = np.asarray(res.pixel_points(), float)
    est = np.asarray(g["exx"], float).ravel()
    ok = np.isfinite(est)
    P, est = P[ok], est[ok]
    t = np.asarray(pair.true_strain(P), float)[:, 0]
    c, r = pair.field.centre, pair.field.radius_mm
    d = np.hypot(P[:, 0] - c[0], P[:, 1] - c[1])
    inl, bg = d < 0.6 * r, (d > 1.5 * r) & (d < 2.5 * r)
    return float(est[bg].mean() / est[inl].mean()), float(t[bg].mean() / t[inl].mean())


def register_with_factor(pair, factor):
    """Register with the beam factor of the default alpha fixed at ``factor``."""
    keep = G.default_beam_alpha_factor
    G.default_beam_alpha_factor = lambda frame, dr, ds: float(factor)
    try:
        return femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin,
                               geometry=pair.geometry)
    finally:
        G.default_beam_alpha_factor = keep


def cases(a):
    pitches = a.pitches or ((0.35, 0.6, 0.85) if not a.quick else (0.6,))
    lpbs = a.lpbs or ((2.0, 3.0, 4.5) if not a.quick else (2.0, 4.5))
    return [(p, b) for p in pitches for b in lpbs]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--probe", default="paper")
    ap.add_argument("--fields", nargs="+", default=["compression", "inclusion"])
    ap.add_argument("--factors", type=float, nargs="+", default=list(FACTORS))
    ap.add_argument("--pitches", type=float, nargs="+")
    ap.add_argument("--lpbs", type=float, nargs="+", help="lines per beam")
    ap.add_argument("--level", type=float, default=0.01, help="compression of both fields (fraction)")
    ap.add_argument("--radius", type=float, default=50.0, help="convex radius mm")
    ap.add_argument("--json", help="append each row (one JSON object a line) here")
    a = ap.parse_args(argv)
    # the beam's width from lines_per_beam alone (the probe's own width below every case's)
    probe = replace(as_probe(a.probe), beam_fwhm_mm=0.05)
    fields = dict(compression=F.compression(a.level), inclusion=F.Inclusion("stiff", "plane-strain", a.level))
    geo_r = a.radius
    print("| pitch deg | line spacing mm | lines per beam | cell lines | field | seed | factor | alpha | "
          "total strain error % | strain ratio (true) | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for pitch, lpb in cases(a):
        geo = femreg.Convex(geo_r, pitch)
        for fname in a.fields:
            for seed in a.seeds:
                pair = make_beam_pair(fields[fname], geo, probe=probe, depth_mm=40, n_rays=int(round(32 / pitch)),
                                      seed=seed, lines_per_beam=lpb)
                rho_c, (_, ds), _ = G.sample_space(geo, pair.ref.shape, pair.spacing[0], pair.origin[0])
                cell = G.lateral_cell_lines(pair.ref)
                old = G.beam_alpha_factor(ds)           # the line spacing alone
                new = G.default_beam_alpha_factor(pair.ref, pair.spacing[0], ds)
                for fac in sorted(set(a.factors) | {round(old, 3), round(new, 3)}):
                    t = time.perf_counter()
                    res = register_with_factor(pair, fac)
                    dt = time.perf_counter() - t
                    e = 100 * field_errors(res, pair.true_displacement, pair.true_strain)["e"]
                    sr, srt = strain_ratio(res, pair) if fname == "inclusion" else (math.nan, math.nan)
                    row = dict(pitch=pitch, ds=ds, lpb=lpb, cell_lines=cell, field=fname, seed=seed, factor=fac,
                               old_factor=old, new_factor=new, level=a.level, radius=geo_r, alpha=res.alpha, e=e,
                               sr=sr, sr_true=srt, success=bool(res.success), probe=a.probe, s=dt)
                    print(f"| {pitch} | {ds:.3f} | {lpb:g} | {cell:.2f} | {fname} | {seed} | {fac:g} | "
                          f"{res.alpha:.3g} | {e:.2f} | {sr:.3f} ({srt:.3f}) | {dt:.1f} |", flush=True)
                    if a.json:
                        with open(a.json, "a") as fh:
                            fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
