"""Strain recovery on the robustness benchmark's pairs: element strain, the nodal average and the projection
(:func:`femreg.fields.recovered_strains`) scored on the same R_P_sigma registrations.

For every pair (the sequence left out): the total strain error of :mod:`benchmarks.robustness` (same ROI and
metric) of the three strains; for the inclusion pairs also the shape of the axial strain's contour at half the
inclusion contrast (midway between the true mean inside 0.7 R and in the ring 1.6-2.2 R): its radius along 72
rays from the centre against the true field's contour, RMS in units of R.  One registration per pair, the
strains evaluated from its displacement.

Run: ``python benchmarks/recovery.py [--cases WORDS]`` (about 1 min on 2 cores); prints a Markdown table.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.robustness import CASES, errors, make_data, roi_slices, truth  # noqa: E402
from femreg.metrics import contour_radii  # noqa: E402

STRAINS = ("element", "average", "projection")


def grids(res):
    """{strain: pixel-grid fields} of one registration."""
    from femreg.fields import recovered_strains

    out = {"element": res.on_grid("element")}
    for method in ("average", "projection"):
        res._nodal_strain, res._grid = recovered_strains(res.mesh.p, res.mesh.t, res.u, method), None
        out[method] = res.on_grid()
    res._nodal_strain, res._grid = None, None
    return out


def run(cases):
    import femreg

    rows = []
    for case in cases:
        data = make_data(case)
        res = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin,
                              regularizer="momentum-stress")
        sl = roi_slices(res.shape, res.spacing)
        tr = truth(data, case, sl)
        g = grids(res)
        row = {"case": case.name, **{s: errors(g[s], tr, sl, 1.54 / data.probe.f0_mhz)["e"] for s in STRAINS}}
        f = data.field
        if hasattr(f, "radius_mm"):
            C, R = f.centre, f.radius_mm
            P = res.pixel_points()
            et = f.strain(P)[:, 0].reshape(res.shape)
            r = np.hypot(P[:, 0] - C[0], P[:, 1] - C[1]).reshape(res.shape)
            level = 0.5 * (np.nanmean(et[(r > 1.6 * R) & (r < 2.2 * R)]) + np.nanmean(et[r < 0.7 * R]))
            rt = contour_radii(et, res.spacing, res.origin, C, R, level, step=0.01)
            for s in STRAINS:
                rr = contour_radii(g[s]["exx"], res.spacing, res.origin, C, R, level, step=0.01)
                row["shape_" + s] = float(np.sqrt(np.nanmean((rr - rt) ** 2)) / R)
        rows.append(row)
        print(_line(row), flush=True)
    return rows


def _line(row):
    e = " | ".join(f"{100 * row[s]:.2f}" for s in STRAINS)
    sh = " | ".join(f"{row['shape_' + s]:.3f}" if "shape_" + s in row else "" for s in STRAINS)
    return f"| {row['case']} | {e} | {100 * (row['projection'] - row['average']):+.2f} | {sh} |"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--seed", type=int, default=0, help="scatterer and noise seed of every pair (default 0)")
    args = ap.parse_args(argv)
    words = [w for w in args.cases.split(",") if w]
    cases = [dataclasses.replace(c, seed=args.seed) for c in CASES
             if not c.sequence and (not words or any(w in c.name for w in words))]
    print("| pair | e element % | e average % | e projection % | projection - average | contour RMS / R element "
          "| average | projection |\n|---|---|---|---|---|---|---|---|")
    rows = run(cases)
    inc = [r for r in rows if "shape_average" in r]
    if inc:
        print("\nmean contour RMS / R over the inclusions: " + ", ".join(
            f"{s} {np.mean([r['shape_' + s] for r in inc]):.3f}" for s in STRAINS))
    print("largest rise of the projection over the average: "
          f"{100 * max(r['projection'] - r['average'] for r in rows):+.2f} points")


if __name__ == "__main__":
    main()
