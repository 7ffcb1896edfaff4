"""Strain recovery on the benchmarks' pairs: element strain, the nodal average, the projection and the edge-aware
recovery (:func:`femreg.fields.recovered_strains`) scored on the same R_P_sigma registrations.

One registration per pair (defaults), the four strains evaluated from its displacement.  Suites:

* ``robustness`` (default): the robustness benchmark's pairs (:mod:`benchmarks.robustness`, the sequence left
  out); total strain error (same ROI and metric) and, for the inclusions, the shape of the axial strain's contour at
  half the inclusion contrast (midway between the true mean inside 0.7 R and in the ring 1.6-2.2 R): its radius
  along 72 rays from the centre against the true field's contour, RMS in units of R;
* ``inclusions``: :mod:`benchmarks.inclusion_sizes`' pairs; total strain error, the 10-90 % widths of the axial
  strain's step at the inclusion's deep and right edges and CNR_e (:func:`benchmarks.inclusion_sizes.scores`),
  for the registration and for the exact displacement at the nodes of its mesh (the floor of mesh and recovery);
* ``bands``: :mod:`benchmarks.shear_bands`' pairs; total strain error, slide error and peak ratio of e_xy
  (:func:`benchmarks.shear_bands.band_scores`).

Run: ``python benchmarks/recovery.py [--suite robustness|inclusions|bands] [--cases WORDS] [--seed N]`` (about
1 min per suite on 2 cores); prints a Markdown table and the largest rise of each recovery over the average.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import types
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.robustness import CASES, errors, make_data, roi_slices, truth  # noqa: E402
from femreg.metrics import contour_radii  # noqa: E402

STRAINS = ("element", "average", "projection", "edge")
SUITES = ("robustness", "inclusions", "bands")


def grids(res, u=None):
    """{strain: pixel-grid fields} of one registration (``u``: another displacement on its mesh)."""
    from femreg.fields import recovered_strains
    from femreg.sampling import sample_grid

    u = res.u if u is None else u
    out = {"element": sample_grid(u, res.locator, res.pixel_grid, "element")}
    for method in STRAINS[1:]:
        out[method] = sample_grid(u, res.locator, res.pixel_grid, "recovered",
                                  nodal_strain=recovered_strains(res.mesh.p, res.mesh.t, u, method))
    return out


def _contour_shapes(res, data, g):
    f = data.field
    C, R = f.centre, f.radius_mm
    P = res.pixel_points()
    et = f.strain(P)[:, 0].reshape(res.shape)
    r = np.hypot(P[:, 0] - C[0], P[:, 1] - C[1]).reshape(res.shape)
    level = 0.5 * (np.nanmean(et[(r > 1.6 * R) & (r < 2.2 * R)]) + np.nanmean(et[r < 0.7 * R]))
    rt = contour_radii(et, res.spacing, res.origin, C, R, level, step=0.01)
    out = {}
    for s in STRAINS:
        rr = contour_radii(g[s]["exx"], res.spacing, res.origin, C, R, level, step=0.01)
        out[s] = float(np.sqrt(np.nanmean((rr - rt) ** 2)) / R)
    return out


def score_case(suite, case):
    """Rows (dicts) of one pair: per strain, the total strain error ``e`` (%) and the suite's extra scores."""
    import femreg
    from forward.pairs import PROBES

    data = make_data(case)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin)
    sl = roi_slices(res.shape, res.spacing)
    tr = truth(data, case, sl)
    lam = PROBES[case.probe].wavelength_mm
    variants = [("registration", None)]
    if suite == "inclusions":
        variants.append(("exact u", np.asarray(data.true_displacement(res.mesh.p.T), float).ravel()))
        full = truth(data, case, (slice(0, res.shape[0], 1), slice(0, res.shape[1])))["exx"]
    rows = []
    for label, u in variants:
        g = grids(res, u)
        row = {"case": case.name, "u": label}
        for s in STRAINS:
            row[s] = {"e": 100 * errors(g[s], tr, sl, lam)["e"]}
        if suite == "robustness" and hasattr(data.field, "radius_mm"):
            for s, v in _contour_shapes(res, data, g).items():
                row[s]["shape"] = v
        if suite == "inclusions":
            from benchmarks.inclusion_sizes import scores

            for s in STRAINS:
                row[s].update(scores(np.asarray(g[s]["exx"], float), data, data.field, full))
        if suite == "bands":
            from benchmarks.shear_bands import band_scores

            for s in STRAINS:
                b = band_scores(g[s], types.SimpleNamespace(origin=data.origin, spacing=data.spacing, ref=data.ref),
                                data.field, sl)
                row[s].update(slide_err=100 * b["slide_err"], peak=b["peak_ratio"])
        rows.append(row)
    return rows


def _line(row, keys):
    cells = [" / ".join(f"{row[s].get(k, float('nan')):.2f}" for s in STRAINS) for k in keys]
    return f"| {row['case']} | {row['u']} | " + " | ".join(cells) + \
        f" | {row['edge']['e'] - row['average']['e']:+.2f} |"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", choices=SUITES, default="robustness")
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--seed", type=int, default=0, help="added to every pair's scatterer and noise seed")
    args = ap.parse_args(argv)
    if args.suite == "inclusions":
        from benchmarks.inclusion_sizes import CASES as cases
    elif args.suite == "bands":
        from benchmarks.shear_bands import CASES as cases
    else:
        cases = [c for c in CASES if not c.sequence]
    words = [w for w in args.cases.split(",") if w]
    cases = [dataclasses.replace(c, seed=c.seed + args.seed) for c in cases
             if not words or any(w in c.name for w in words)]
    keys = {"robustness": ("e", "shape"), "inclusions": ("e", "edge_ax", "edge_lat", "cnr"),
            "bands": ("e", "slide_err", "peak")}[args.suite]
    print(f"each cell: {' / '.join(STRAINS)}\n\n| pair | u | " + " | ".join(keys) + " | e edge - average |\n"
          + "|---" * (len(keys) + 3) + "|")
    rows = []
    for case in cases:
        for row in score_case(args.suite, case):
            rows.append(row)
            print(_line(row, keys), flush=True)
    reg = [r for r in rows if r["u"] == "registration"]
    for s in ("projection", "edge"):
        rise = max(reg, key=lambda r: r[s]["e"] - r["average"]["e"])
        print(f"largest rise of {s} over the average: {rise[s]['e'] - rise['average']['e']:+.2f} points "
              f"({rise['case']})")


if __name__ == "__main__":
    main()
