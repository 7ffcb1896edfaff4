"""Strain-edge width where the true strain steps: bonded layers in plane stress, femreg and its peers on the same
pairs.

A bonded disk is a poor ruler for the sharpness of a strain image: in a nearly incompressible solid the strain
does not step at its interface but changes over a near field of about the radius (the true 10-90 % width of the
axial strain at the deep edge of a 3 mm disk is 0.97 mm, at 8 mm 2.48 mm; ``benchmarks/inclusion_sizes.py``), so
a width measured there is mostly the truth's own.  Layers parallel to the probe face under plane stress
(:class:`forward.fields.Layers`) are a true step of e_xx at every interface: the width measured there is what the
method adds.

Columns side by side that slide along vertical interfaces (:class:`forward.fields.SlidingColumns`, the ``col_``
cases) are the lateral ruler: a bonded interface cannot carry a lateral step of e_xx, a frictionless one does.
There the true shear strain is a line (the slip), which the total strain error counts against every method alike;
the e_xx error does not.

Per case x method (``e`` over the robustness ROI, :func:`benchmarks.robustness.errors`):

* ``edge``: 10-90 % width (mm) of e_xx across each interface (:func:`femreg.metrics.edge_width`, levels the true
  plateaus), on every image column (row, for the columns' interfaces) inside the ROI, within ``+-min(4 mm, half the
  distance to the next interface)`` of it; the median over the lines, then the worst interface;
* ``edge (mean)``: the same on the lateral mean profile (what a plot of the mean over the ROI shows);
* ``shift``: depth of the measured 50 % crossing less the interface's (median over columns, mean |.| over the
  interfaces), mm;
* ``slip err``: the columns' slip, the jump of u_x 2.5 mm either side of each vertical interface against the true
  one, summed over the ROI's rows (:func:`slip_error`; nan for layers).

Rows: femreg's defaults ("R_P_sigma"), ``refine=None``, the true displacement on the defaults' refined mesh
recovered as femreg's (the floor that mesh sets, no registration) and the robustness benchmark's peers.

Run: ``python benchmarks/layer_edges.py [--cases ...] [--methods ...] [--out out/layer_edges]``; writes
``results.md`` and one picture per case (e_xx of the truth and of every method) to the ``--out`` folder.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.inclusion_sizes import EXACT_ON_MESH, method_runs, selected, write_results  # noqa: E402
from benchmarks.robustness import PEER_METHODS, Case, draw_case, errors, make_data, roi_slices, truth  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import PROBES  # noqa: E402


def _layers(interfaces, moduli, level):
    return lambda: F.Layers(interfaces, moduli, level)


CASES = [
    Case("soft10_1pc_paper", _layers((15.0, 25.0), (1.0, 0.25, 1.0), 0.01), "paper", (30, 30), 20, top_mm=5.0),
    Case("soft10_1pc_L7", _layers((15.0, 25.0), (1.0, 0.25, 1.0), 0.01), "L7", (30, 30), 20, top_mm=5.0),
    Case("stiff8_3pc_L7", _layers((16.0, 24.0), (1.0, 4.0, 1.0), 0.03), "L7", (30, 30), 25, top_mm=5.0, seed=3),
    Case("soft6_2pc_L12", _layers((17.0, 23.0), (1.0, 0.25, 1.0), 0.02), "L12", (25, 25), 25, top_mm=7.5,
         seed=5),
    Case("step_2pc_paper", _layers((20.0,), (2.0, 0.5), 0.02), "paper", (30, 30), 25, top_mm=5.0, seed=2),
    Case("stiff8_1pc_L15", _layers((16.0, 24.0), (1.0, 2.0, 1.0), 0.01), "L15", (20, 20), 20, top_mm=10.0,
         seed=7),
    # under 5 MHz (outside the resolution target): the 3 MHz probe's axial PSF is twice the paper probe's
    Case("soft10_2pc_L3", _layers((15.0, 25.0), (1.0, 0.25, 1.0), 0.02), "L3", (30, 30), 20, top_mm=5.0, seed=1),
    # held out: drawn after the interface rule (femreg.refine.Refinement.fine_layer), before its full solve
    # (fine_layer_full) was chosen, and not used to choose it
    Case("held_three_2pc_L7", _layers((12.0, 20.0, 28.0), (1.0, 3.0, 0.5, 1.0), 0.02), "L7", (35, 30), 25,
         top_mm=3.0, seed=11),
    Case("held_thin3_1pc_paper", _layers((18.0, 21.0), (1.0, 4.0, 1.0), 0.01), "paper", (30, 30), 20, top_mm=5.0,
         seed=12),
    Case("held_skin_1.5pc_L12", _layers((8.0,), (0.5, 1.0), 0.015), "L12", (20, 20), 25, top_mm=3.0, seed=13),
    Case("held_soft5_4pc_L7", _layers((13.0, 18.0), (1.0, 0.3, 1.0), 0.04), "L7", (30, 30), 30, top_mm=3.0,
         seed=14),
    Case("held_deep_3pc_L3", _layers((20.0, 32.0), (1.0, 2.0, 1.0), 0.03), "L3", (40, 40), 20, top_mm=5.0, seed=15),
    Case("held_L15_0.5pc", _layers((14.0, 17.0), (1.0, 0.5, 1.0), 0.005), "L15", (15, 15), 30, top_mm=8.0,
         seed=16),
]



def _columns(interfaces, moduli, level, model="plane-stress"):
    return lambda: F.SlidingColumns(interfaces, moduli, level, model=model)


# lateral steps: columns sliding along vertical interfaces (a bonded interface carries no lateral step of e_xx);
# the slip grows with depth from the probe face, 0.10-0.22 mm at the image's bottom here
CASES += [
    Case("col_soft10_0.5pc_paper", _columns((-5.0, 5.0), (1.0, 0.5, 1.0), 0.005), "paper", (30, 30), 20,
         top_mm=5.0, seed=21),
    Case("col_stiff8_1pc_L7", _columns((-4.0, 4.0), (1.0, 2.0, 1.0), 0.01), "L7", (30, 30), 25, top_mm=5.0,
         seed=22),
    Case("col_step_0.5pc_L12", _columns((1.0,), (1.5, 0.75), 0.005), "L12", (25, 25), 25, top_mm=5.0, seed=23),
    Case("col_soft6_0.5pc_L15", _columns((-3.0, 3.0), (1.0, 0.5, 1.0), 0.005), "L15", (20, 20), 30, top_mm=5.0,
         seed=24),
    Case("col_pstrain_0.5pc_paper", _columns((-6.0, 4.0), (1.0, 0.6, 1.5), 0.005, "plane-strain"), "paper",
         (35, 30), 25, top_mm=5.0, seed=25),
    Case("col_step_1pc_L3", _columns((-2.0,), (1.0, 0.6), 0.01), "L3", (40, 40), 20, top_mm=5.0, seed=26),
    # held out: drawn after the slip rule (femreg.refine.beam_slip_lines) was set, to choose the split at a slip
    Case("held_col_soft_0.5pc_L7", _columns((-3.0, 4.0), (1.0, 0.6, 1.0), 0.005), "L7", (30, 30), 25, top_mm=4.0,
         seed=31),
    Case("held_col_step_0.5pc_paper", _columns((2.0,), (0.7, 1.4), 0.005), "paper", (30, 30), 25, top_mm=6.0,
         seed=32),
    Case("held_col_stiff_1pc_L3", _columns((-5.0, 5.0), (1.0, 1.8, 1.0), 0.01), "L3", (40, 40), 20, top_mm=5.0,
         seed=33),
    Case("held_col_step_0.5pc_L7_deep", _columns((0.0,), (1.0, 0.6), 0.005), "L7", (30, 30), 30, top_mm=10.0,
         seed=34),
    Case("held_col_pstrain_1pc_L12", _columns((-2.0, 2.5), (1.0, 0.5, 1.0), 0.01, "plane-strain"), "L12",
         (20, 20), 25, top_mm=5.0, seed=35),
    # slips of 0.02-0.04 mm (moduli 1 / 0.9), below the first shear test of the slip rule
    Case("col_tiny_0.5pc_L7", _columns((0.0,), (1.0, 0.9), 0.005), "L7", (30, 30), 25, top_mm=5.0, seed=56),
    Case("col_tiny_1pc_paper", _columns((-3.0,), (1.0, 0.9), 0.01), "paper", (30, 30), 25, top_mm=5.0, seed=58),
]
FEMREG = ["R_P_sigma", "R_P_sigma no refine"]
METHODS = FEMREG + [EXACT_ON_MESH] + list(PEER_METHODS)


def _plateaus(field):
    """(axis across the interfaces, interface positions mm, e_xx on each side) of a layered or column field."""
    if isinstance(field, F.SlidingColumns):
        return 1, field.interfaces_mm, field.exx_columns
    return 0, field.interfaces_mm, field.exx_layers


def edge_scores(exx, data, field) -> dict:
    """``edge``, ``edge_mean``, ``shift`` (mm) of an e_xx image (module docstring): across the layers' interfaces
    along depth, across the columns' interfaces laterally."""
    from femreg.metrics import edge_width

    axis, z, plateau = _plateaus(field)
    sl = roi_slices(data.ref.shape, data.spacing)
    x = data.origin[axis] + np.arange(data.ref.shape[axis]) * data.spacing[axis]
    along = np.arange(data.ref.shape[axis])[sl[axis]]
    lines = np.arange(data.ref.shape[1 - axis])[sl[1 - axis]]
    img = exx if axis == 0 else exx.T
    x_lo, x_hi = x[along[0]], x[along[-1]]
    bounds = np.r_[x_lo, z, x_hi]
    widths, means, shifts = [], [], []
    for k, d in enumerate(z):
        w = min(4.0, 0.5 * (d - bounds[k]), 0.5 * (bounds[k + 2] - d))
        sel = (x >= d - w) & (x <= d + w)
        lo, hi = plateau[k], plateau[k + 1]
        per_line, mids = [], []
        for j in lines:
            prof = img[sel, j]
            if not np.all(np.isfinite(prof)):
                continue
            try:
                per_line.append(edge_width(x[sel], prof, levels=(lo, hi)))
            except ValueError:
                per_line.append(np.nan)
            f = (prof - lo) / (hi - lo)
            up = np.nonzero((f[:-1] < 0.5) & (f[1:] >= 0.5))[0]
            if up.size:
                i = up[0]
                mids.append(x[sel][i] + (0.5 - f[i]) / (f[i + 1] - f[i]) * (x[sel][i + 1] - x[sel][i]) - d)
        pc = np.asarray(per_line, float)
        # a line whose profile never spans the step counts as infinitely wide (the median then reads it)
        widths.append(float(np.median(np.where(np.isfinite(pc), pc, np.inf))) if pc.size else np.nan)
        try:
            means.append(edge_width(x[sel], np.nanmean(img[sel][:, lines], axis=1), levels=(lo, hi)))
        except ValueError:
            means.append(np.nan)
        shifts.append(abs(float(np.median(mids))) if mids else np.nan)
    return dict(edge=max(widths), edge_mean=max(means), shift=float(np.mean(shifts)))


def slip_error(ux, data, field, reach_mm: float = 2.5) -> float:
    """Relative error of the slip across each vertical interface of a column field (NaN for layers): the jump of
    the measured u_x between ``reach_mm`` either side of the interface (outside the blur of about a beam width),
    against the true jump at the same two points, summed over the ROI's rows and the interfaces
    (sum |measured - true| / sum |true|)."""
    if not isinstance(field, F.SlidingColumns):
        return float("nan")
    sl = roi_slices(data.ref.shape, data.spacing)
    x = data.origin[0] + np.arange(data.ref.shape[0])[sl[0]] * data.spacing[0]
    y = data.origin[1] + np.arange(data.ref.shape[1]) * data.spacing[1]
    num = den = 0.0
    for d in field.interfaces_mm:
        lo, hi = int(np.argmin(np.abs(y - (d - reach_mm)))), int(np.argmin(np.abs(y - (d + reach_mm))))
        meas = np.asarray(ux, float)[sl[0], hi] - np.asarray(ux, float)[sl[0], lo]
        pts = lambda j: np.column_stack([x, np.full(x.size, y[j])])      # noqa: E731
        true = field.displacement(pts(hi))[:, 0] - field.displacement(pts(lo))[:, 0]
        ok = np.isfinite(meas)
        num += float(np.sum(np.abs(np.where(ok, meas, 0.0) - true)))
        den += float(np.sum(np.abs(true)))
    return num / den if den > 0 else float("nan")


def main(argv=None):
    cases, methods, out = selected(argv, CASES, METHODS, "out/layer_edges", __doc__.split("\n\n")[0])
    lines = ["| case | method | total strain err % | e_xx err % | edge (median of lines) mm | edge (mean profile) mm "
             "| 50 % shift mm | slip err % | CPU s |\n", "|---|---|---|---|---|---|---|---|---|\n"]
    for case in cases:
        data = make_data(case)
        field = data.field
        sl = roi_slices(data.ref.shape, data.spacing)
        full = (slice(0, data.ref.shape[0], 1), slice(0, data.ref.shape[1]))
        ts = edge_scores(truth(data, case, full)["exx"], data, field)
        lines.append(f"| {case.name} | truth | 0 | 0 | {ts['edge']:.2f} | {ts['edge_mean']:.2f} | 0 | 0 | |\n")
        troi = truth(data, case, sl)
        grids, results = {}, {}
        for method, g, dt in method_runs(case, data, methods):
            s = edge_scores(np.asarray(g["exx"], float), data, field)
            err = errors(g, troi, sl, PROBES[case.probe].wavelength_mm)
            e = err["e"]
            lines.append(f"| {case.name} | {method} | {100 * e:.1f} | {100 * err['exx']:.1f} | {s['edge']:.2f} | "
                         f"{s['edge_mean']:.2f} | "
                         f"{s['shift']:.2f} | {100 * slip_error(g['ux'], data, field):.1f} | {dt:.1f} |\n")
            print(lines[-1], end="", flush=True)
            # the columns' pictures give the e_xx error (their truth's shear strain is a line, the slip)
            shown = err["exx"] if isinstance(field, F.SlidingColumns) else e
            grids[method], results[method] = g, dict(e=shown, time_s=dt)
        # e_xx of the truth and of every method, one picture per case (the robustness benchmark's layout)
        t_exx = truth(data, case, full)["exx"]
        out.mkdir(parents=True, exist_ok=True)
        notes = field.name + (" (e: e_xx error)" if isinstance(field, F.SlidingColumns) else "")
        draw_case(out / f"{case.name}.png", dataclasses.replace(case, notes=notes), data, grids, results,
                  dict(exx=t_exx, exx_img=100 * t_exx))
    write_results(lines, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
