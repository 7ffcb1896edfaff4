"""Steps in the shear-strain (e_xy) picture on refined (graded) meshes: where they come from.

Per pair (shear bands of ``benchmarks/shear_bands.py`` and inclusions of ``benchmarks/inclusion_sizes.py``) one
registration with the defaults, and its strain recovered several ways from the same nodal displacement, sampled on
the reference pixel grid as ``RegistrationResult.on_grid`` does:

* ``reg plain`` / ``reg graded``: the registration's displacement, the default adaptive recovery
  (:func:`femreg.fields.adaptive_strains`, its nodal average weighting the element strains equally) / the same
  with the average weighted by 1 / element area (:func:`femreg.fields.graded_weights`);
* ``reg avg plain`` / ``reg avg graded``: the same with the average alone (adaptive weight 0);
* ``exact plain`` / ``exact graded`` (and ``exact avg ...``): the true displacement at the same mesh's nodes,
  recovered alike -- what mesh, recovery and sampling alone do to the picture;
* ``element``: the raw element gradient (``strain="element"``).

Scores over the robustness ROI samples (:func:`benchmarks.robustness.roi_slices`): ``e`` the total strain error %
(:func:`benchmarks.robustness.errors`), ``exy`` the relative L2 error % of e_xy, and ``rough x`` / ``rough y``: the
RMS of the second differences of the e_xy image along x (axial) / y (lateral) over the truth's own, counted only
away from the truth's sharp features (pixels within 8 samples of the truth's top 3 % of second differences left
out: an inclusion's rim, a band's faces), i.e. how much staircase and element-scale texture the smooth parts of
the picture carry (1: as rough as the truth; a band's truth has none, so its lateral roughness is given in
strain, ``abs``).

Run: ``python benchmarks/exy_staircase.py [--cases r3,band2] [--out out/exy_staircase]``.
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import inclusion_sizes as IS  # noqa: E402
from benchmarks import shear_bands as SB  # noqa: E402
from benchmarks.robustness import errors, make_data, roi_slices, truth  # noqa: E402
from forward.pairs import PROBES  # noqa: E402

DEFAULT_CASES = ("band2_s0.3_d15_L7", "held_band3_s0.4_d12_L3", "r3_4pc_L7", "r8_2pc_paper", "held_r2_2pc_L3")


def graded_recovery(p, t, u, w):
    """femreg's adaptive recovery (:func:`femreg.fields.adaptive_strains`, weight ``w``) with its nodal average's
    element strains weighted by 1 / element area (:func:`femreg.fields.graded_weights`)."""
    from femreg import fields as FL

    return FL.adaptive_strains(p, t, u, weight=w, cell_weights=FL.graded_weights(p, t))


def roughness(img, t_exy):
    """(x, y) RMS second differences of ``img`` away from the truth's sharp features, and the truth's own."""
    from scipy.ndimage import binary_dilation

    d2 = np.zeros_like(t_exy)
    d2[1:-1] += np.abs(np.diff(t_exy, 2, 0))
    d2[:, 1:-1] += np.abs(np.diff(t_exy, 2, 1))
    sharp = binary_dilation(d2 > np.percentile(d2, 97), iterations=8)
    mx = ~(sharp[:-2] | sharp[1:-1] | sharp[2:])
    my = ~(sharp[:, :-2] | sharp[:, 1:-1] | sharp[:, 2:])

    def r(a):
        return (float(np.sqrt(np.mean(np.diff(a, 2, 0)[mx] ** 2))),
                float(np.sqrt(np.mean(np.diff(a, 2, 1)[my] ** 2))))
    return r(img), r(t_exy)


def run(names, out: Path):
    import femreg
    from femreg import fields as FL
    from femreg.sampling import sample_grid

    out.mkdir(parents=True, exist_ok=True)
    cases = {c.name: c for c in SB.CASES + IS.CASES}
    rows = []
    for nm in names:
        case = cases[nm]
        data = make_data(case)
        sl = roi_slices(data.ref.shape, data.spacing)
        tr = truth(data, case, sl)
        lam = PROBES[case.probe].wavelength_mm
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin)
        w = res.recovery_weight
        p, t, u = res.mesh.p, res.mesh.t, res.u
        ue = np.asarray(data.true_displacement(p.T), float).ravel()

        def grid(uu, ns=None):
            if ns is None:
                return sample_grid(uu, res.locator, res.pixel_grid, "element")
            return sample_grid(uu, res.locator, res.pixel_grid, "recovered", nodal_strain=ns)
        grids = {"reg plain": grid(u, FL.adaptive_strains(p, t, u, w)),
                 "reg graded": grid(u, graded_recovery(p, t, u, w)),
                 "reg avg plain": grid(u, FL.adaptive_strains(p, t, u, 0.0)),
                 "reg avg graded": grid(u, graded_recovery(p, t, u, 0.0)),
                 "exact plain": grid(ue, FL.adaptive_strains(p, t, ue, w)),
                 "exact graded": grid(ue, graded_recovery(p, t, ue, w)),
                 "exact avg plain": grid(ue, FL.adaptive_strains(p, t, ue, 0.0)),
                 "exact avg graded": grid(ue, graded_recovery(p, t, ue, 0.0)),
                 "element": grid(u)}
        for k, g in grids.items():
            img = np.nan_to_num(np.asarray(g["exy"], float)[sl])
            (rx, ry), (tx, ty) = roughness(img, tr["exy"])
            row = dict(case=nm, recovery=k, weight=round(w, 3), n_el=int(t.shape[1]),
                       e=100 * errors(g, tr, sl, lam)["e"],
                       exy=100 * float(np.sqrt(np.sum((img - tr["exy"]) ** 2) / np.sum(tr["exy"] ** 2))),
                       rough_x=rx / tx if tx > 0 else float("nan"),
                       rough_y=ry / ty if ty > 0 else float("nan"), rough_y_abs=ry)
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = ["| case | recovery | w | e % | e_xy % | rough x | rough y |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        ry = f"{r['rough_y']:.2f}" if np.isfinite(r["rough_y"]) else f"abs {r['rough_y_abs']:.1e}"
        lines.append(f"| {r['case']} | {r['recovery']} | {r['weight']:.2f} | {r['e']:.2f} | {r['exy']:.2f} | "
                     f"{r['rough_x']:.2f} | {ry} |")
    (out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES), help="comma-separated case names")
    ap.add_argument("--out", default="out/exy_staircase")
    a = ap.parse_args(argv)
    run([c for c in a.cases.split(",") if c], Path(a.out))


if __name__ == "__main__":
    main()
