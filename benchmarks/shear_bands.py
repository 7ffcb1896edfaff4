"""Shear-band benchmark: two layers sliding laterally past each other across a band parallel to the probe face
(:class:`forward.fields.ShearBand`, on 1 % axial compression), several depths, thicknesses, slides and two probes;
femreg and the peers of the robustness benchmark on the same pairs.

Per case x method, over the robustness benchmark's ROI (:func:`benchmarks.robustness.roi_slices`), from the lateral
median of the method's e_xy against depth (:func:`femreg.metrics.depth_profile`) within the band +- 3 mm
(:func:`femreg.metrics.shear_band_metrics`):

* ``slide_err``: (measured slide - true slide) / true slide, the slide = integral of 2 e_xy across the band;
* ``depth_err``: measured band centre - true centre (mm);
* ``peak_ratio``: measured peak e_xy / true peak e_xy (``slide / (2 t)``);
* ``fwhm``: width of the measured band (mm), ``edge``: 10-90 % width of its upper face, from 0 to the measured peak
  (mm; true: 0, the band's faces are steps);
* ``e``: total strain error of the robustness benchmark (relative L2 with ``e:e``, shear counted twice);
  ``uy``: relative L2 error of the lateral displacement (defined for a displacement jump too).

Methods: femreg R_P_sigma with defaults (adaptive refinement and its local relaxation included,
:mod:`femreg.refine`), the same without refinement ("R_P_sigma no refine", ``refine=None``), the two-pass refinement
without its relaxation ("R_P_sigma no relax", ``Refinement(relax=None)``) and with alpha / 10
(``alpha=0.1 * default``), "R_P_sigma slip"
(:func:`femreg.shear.slip_settings`: thin axial elements, 0.35 mm, at the default weight per area and
``regularizer_options={"shear_traction": 0.03}``, the momentum regulariser's tangential traction jump weighted
down so that layers may slide), "R_P_sigma refine+slip"
(:data:`femreg.refine.SLIP_REFINEMENT`: three passes, and the tangential traction weight 0.03 only where the
shear-traction jump stands out), "R_P_sigma refine deep"
(:func:`benchmarks.refine_cost.deep_refinement`: :data:`femreg.refine.DEEP_REFINEMENT`, which the defaults use too),
"R_P_sigma face rows" (the defaults with
:attr:`femreg.refine.Refinement.face_rows`: the row break nearest each strain step of the refined solve moved onto
it, and that pass solved again; its strain the default recovery, the element gradient ("... element") or the
edge-aware recovery ("... edge", ``on_grid(recovery="edge")``)), the peers
(:mod:`benchmarks.peers`: NCC block matching, SimpleITK B-spline, scikit-image TV-L1; a peer whose package is
missing is reported as such).

The ``held_`` cases were drawn before the relaxation's constants were chosen and were not used for them.

Run: ``python benchmarks/shear_bands.py`` (``--cases L7`` selects cases whose name contains a word; ``--methods``
likewise, a method's full name selects that method alone; ``--out`` default ``out/shear_bands``: ``results.csv``, ``results.md``).
"""
from __future__ import annotations

import argparse
import dataclasses
import csv
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.robustness import PEER_METHODS, Case, errors, make_data, roi_slices, truth  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import PROBES  # noqa: E402


def _band(depth, thickness, slide):
    return lambda: F.ShearBand(depth, thickness, slide, 0.01)


CASES = [
    Case("band1_s0.15_d8_L7", _band(8.0, 1.0, 0.15), "L7", (30, 30), 30),
    Case("band1_s0.15_d15_L7", _band(15.0, 1.0, 0.15), "L7", (30, 30), 30),
    Case("band1_s0.15_d24_L7", _band(24.0, 1.0, 0.15), "L7", (30, 30), 30),
    Case("band2_s0.3_d15_L7", _band(15.0, 2.0, 0.3), "L7", (30, 30), 30),
    Case("band0.5_s0.05_d15_L7", _band(15.0, 0.5, 0.05), "L7", (30, 30), 30),
    Case("band1_s0.1_d12_paper", _band(12.0, 1.0, 0.1), "paper", (35, 30), 20),
    Case("band2_s0.3_d20_paper", _band(20.0, 2.0, 0.3), "paper", (35, 30), 20),
    Case("band1_s0.15_d28_paper", _band(28.0, 1.0, 0.15), "paper", (35, 30), 20),
    # held out from the choice of the relaxation's constants (femreg.refine.Refinement.relax): drawn before it
    Case("held_band1.5_s0.2_d18_L12", _band(18.0, 1.5, 0.2), "L12", (30, 30), 25),
    Case("held_band3_s0.4_d12_L3", _band(12.0, 3.0, 0.4), "L3", (40, 40), 25),
    Case("held_band2_s0.2_d25_L7", _band(25.0, 2.0, 0.2), "L7", (30, 30), 20),
]

FEMREG = ("R_P_sigma", "R_P_sigma no refine", "R_P_sigma no relax", "R_P_sigma alpha/10", "R_P_sigma slip",
          "R_P_sigma refine+slip", "R_P_sigma refine deep", "R_P_sigma interface", "R_P_sigma face rows",
          "R_P_sigma face rows element", "R_P_sigma face rows edge")
#: ``refine=`` of the variants that set it (:mod:`femreg.refine`; the others: register's default)
REFINE = {"R_P_sigma no refine": None, "R_P_sigma no relax": "norelax", "R_P_sigma refine+slip": "slip",
          "R_P_sigma refine deep": "deep", "R_P_sigma face rows": "face", "R_P_sigma face rows element": "face",
          "R_P_sigma face rows edge": "face"}
METHODS = list(FEMREG) + list(PEER_METHODS)
WINDOW_MM = 3.0


def run_method(method, data):
    """(grids, seconds) of ``method`` on a Pair."""
    import femreg

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if method in FEMREG:
            kw = dict(spacing=data.spacing, origin=data.origin)
            if method.endswith("alpha/10"):
                # the default alpha of this pair: what register chose without one
                kw["alpha"] = 0.1 * femreg.register(data.ref, data.mov, **kw).alpha
            elif method in REFINE:
                from benchmarks.refine_cost import deep_refinement
                from femreg.refine import SLIP_REFINEMENT, Refinement

                kw["refine"] = {"slip": SLIP_REFINEMENT, "norelax": Refinement(relax=None),
                                "deep": deep_refinement(),
                                "face": dataclasses.replace(deep_refinement(), face_rows=True)}.get(REFINE[method], REFINE[method])
            elif method.endswith("slip"):
                from femreg.shear import slip_settings

                kw.update(slip_settings(femreg.register(data.ref, data.mov, **kw)))
            if method.endswith("interface"):
                from femreg.refine import SLIP_REFINEMENT

                g = sliding_interface(data, femreg.register(data.ref, data.mov, refine=SLIP_REFINEMENT, **kw))
            elif method.endswith("rows element"):
                g = femreg.register(data.ref, data.mov, **kw).on_grid("element")
            elif method.endswith("rows edge"):
                g = femreg.register(data.ref, data.mov, **kw).on_grid(recovery="edge")
            else:
                g = femreg.register(data.ref, data.mov, **kw).on_grid()
        else:
            g = PEER_METHODS[method](data.ref, data.mov, data.spacing, data.origin)
    return g, time.perf_counter() - t0


def sliding_interface(data, first):
    """A sliding interface: the layers above and below one detected line registered separately, so that the
    displacement may jump across it (a measurement of the model, not a femreg option).

    The line: the depth of the largest |median e_xy| across the lateral ROI of the registration ``first`` (its
    band; :data:`femreg.refine.SLIP_REFINEMENT`, whose depth is the closest).  The two slabs (mesh top to the line, line to mesh bottom, the full width) are registered with
    femreg's defaults on their own meshes; their grids are joined at the line.  The jump of u between the two
    pixel rows beside the line is spread over the probe's axial pulse-echo resolution (``cycles x wavelength / 2``,
    at least two rows) as a constant strain, the resolution at which the data can place it; the strain is
    ``jump / width`` (e_xx from u_x, 2 e_xy from u_y) added to the slabs' own."""
    import femreg
    from femreg.metrics import depth_profile

    g0 = first.on_grid()
    sl = roi_slices(data.ref.shape, data.spacing)
    prof = np.abs(depth_profile(g0["exy"], columns=sl[1]))
    rows = np.arange(data.ref.shape[0])
    inside = (rows >= sl[0].start) & (rows < sl[0].stop) & np.isfinite(prof)
    i_d = int(rows[inside][np.argmax(prof[inside])])
    dx = float(data.spacing[0])
    d = data.origin[0] + (i_d - 0.5) * dx                     # the line: the upper edge of row i_d
    pts = first.mesh.p
    x0, x1, y0, y1 = float(pts[0].min()), float(pts[0].max()), float(pts[1].min()), float(pts[1].max())
    kw = dict(spacing=data.spacing, origin=data.origin)
    top = femreg.register(data.ref, data.mov, roi=(x0, d, y0, y1), **kw).on_grid()
    bot = femreg.register(data.ref, data.mov, roi=(d, x1, y0, y1), **kw).on_grid()
    g = {}
    for k in ("ux", "uy", "exx", "eyy", "exy"):
        g[k] = np.where(rows[:, None] < i_d, top[k], bot[k])
    width = max(2 * dx, 0.5 * data.probe.cycles * data.probe.wavelength_mm)
    near = np.abs((rows + 0.5 - i_d) * dx) <= width / 2      # the rows the jump is spread over
    with np.errstate(invalid="ignore"):
        jx = bot["ux"][i_d] - top["ux"][i_d - 1]
        jy = bot["uy"][i_d] - top["uy"][i_d - 1]
    w = near.sum() * dx
    g["exx"] = np.where(near[:, None], g["exx"] + jx / w, g["exx"])
    g["exy"] = np.where(near[:, None], g["exy"] + 0.5 * jy / w, g["exy"])
    return g


def band_scores(g, data, band, sl) -> dict:
    """Slide / depth / peak / width / edge of a method's e_xy (module docstring)."""
    from femreg.metrics import depth_profile, edge_width, shear_band_metrics

    x = data.origin[0] + np.arange(data.ref.shape[0]) * data.spacing[0]
    prof = depth_profile(np.asarray(g["exy"], float), columns=sl[1])
    win = (band.depth_mm - band.thickness_mm / 2 - WINDOW_MM, band.depth_mm + band.thickness_mm / 2 + WINDOW_MM)
    m = shear_band_metrics(x, prof, win)
    face = (x >= win[0]) & (x <= band.depth_mm)
    edge = edge_width(x[face], prof[face], levels=(0.0, m["peak"])) if face.sum() >= 3 else float("nan")
    return dict(slide_err=m["slide"] / band.slide_mm - 1.0, depth_err=m["depth"] - band.depth_mm,
                peak_ratio=m["peak"] / band.peak_exy, fwhm=m["fwhm"], edge=edge)


def run(cases, methods, out: Path):
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in cases:
        data = make_data(case)
        band = data.field
        sl = roi_slices(data.ref.shape, data.spacing)
        t = truth(data, case, sl)
        lam = PROBES[case.probe].wavelength_mm
        for method in methods:
            try:
                g, dt = run_method(method, data)
            except ImportError as exc:
                print(f"{case.name} {method}: skipped ({exc})", file=sys.stderr)
                continue
            err = errors(g, t, sl, lam)
            r = dict(case=case.name, method=method, **band_scores(g, data, band, sl), e=err["e"], uy=err["uy"],
                     time_s=dt)
            rows.append(r)
            print(f"{case.name:24s} {method:22s} slide {100 * r['slide_err']:+6.1f} % depth {r['depth_err']:+.2f} mm "
                  f"peak {r['peak_ratio']:.2f} fwhm {r['fwhm']:.2f} edge {r['edge']:.2f} e {100 * r['e']:.1f} % "
                  f"u_y {100 * r['uy']:.1f} % "
                  f"{dt:.1f} s", flush=True)
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["case"])
        w.writeheader()
        w.writerows(rows)
    md = tables(rows)
    (out / "results.md").write_text(md)
    return rows, md


def tables(rows) -> str:
    lines = ["| case | method | slide err % | depth err mm | peak e_xy ratio | FWHM mm | edge 10-90 % mm | "
             "total strain err % | u_y err % | s |\n", "|---|---|---|---|---|---|---|---|---|---|\n"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['method']} | {100 * r['slide_err']:+.1f} | {r['depth_err']:+.2f} | "
                     f"{r['peak_ratio']:.2f} | {r['fwhm']:.2f} | {r['edge']:.2f} | {100 * r['e']:.1f} | {100 * r['uy']:.1f} | "
                     f"{r['time_s']:.1f} |\n")
    return "".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--methods", default="", help="comma-separated words; run methods whose name contains one "
                                                   "(a method's full name: that method only)")
    ap.add_argument("--out", default="out/shear_bands")
    a = ap.parse_args(argv)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    words = [w for w in a.cases.split(",") if w]
    cases = [c for c in CASES if not words or any(w in c.name for w in words)]
    mw = [w for w in a.methods.split(",") if w]
    methods = [m for m in METHODS if not mw or any(w == m or (w not in METHODS and w in m) for w in mw)]
    if not cases or not methods:
        print("no case or method selected", file=sys.stderr)
        return 2
    _, md = run(cases, methods, Path(a.out))
    print("\n" + md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
