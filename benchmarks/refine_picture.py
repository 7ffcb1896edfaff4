"""What the default refinement does to a strain image: one inclusion pair of ``benchmarks/inclusion_sizes.py``
(default: r 3 mm stiff disk at 1 % compression under the paper's 5.5 MHz probe), registered with ``refine=None``
and with the default, e_xx and e_xy of each with the tensor mesh drawn over it, beside the truth.  Prints the total
strain error and the element count of both.

Run: ``python benchmarks/refine_picture.py [--case r3_1pc_paper] [--out docs/refinement_mesh.png]``
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.inclusion_sizes import CASES  # noqa: E402
from benchmarks.robustness import errors, make_data, roi_slices, truth  # noqa: E402
from forward.pairs import PROBES  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="r3_1pc_paper", help="a case name of benchmarks/inclusion_sizes.py")
    ap.add_argument("--out", default="docs/refinement_mesh.png")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import femreg

    case = next((c for c in CASES if c.name == args.case), None)
    if case is None:
        ap.error(f"unknown case {args.case!r}; one of: " + ", ".join(c.name for c in CASES))
    data = make_data(case)
    runs = {}
    for label, refine in (("refine=None", None), ("default refinement", "auto")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            runs[label] = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin, refine=refine)
    res0 = next(iter(runs.values()))
    sl = roi_slices(res0.shape, res0.spacing)
    tr = truth(data, case, sl)
    pts = res0.pixel_points().reshape(res0.shape + (2,))[sl]
    ext = (pts[0, 0, 1], pts[0, -1, 1], pts[-1, 0, 0], pts[0, 0, 0])     # lateral left/right, depth bottom/top (mm)
    fig, axes = plt.subplots(2, 3, figsize=(13, 8.4), constrained_layout=True)
    for i, (key, name) in enumerate((("exx", "axial strain e_xx"), ("exy", "shear strain e_xy"))):
        lim = float(np.max(np.abs(tr[key])))
        panels = [("truth", tr[key], None)]
        for label, res in runs.items():
            e = errors(res.on_grid(), tr, sl, PROBES[case.probe].wavelength_mm)["e"]
            panels.append((f"{label}\n{res.mesh.t.shape[1]} elements, total strain error {100 * e:.1f} %",
                           np.asarray(res.on_grid()[key])[sl], res))
            if i == 0:
                print(f"{case.name} {label}: total strain error {100 * e:.2f} %, {res.mesh.t.shape[1]} elements")
        for ax, (title, img, res) in zip(axes[i], panels):
            im = ax.imshow(img, cmap="RdBu_r", vmin=-lim, vmax=lim, extent=ext, interpolation="nearest")
            if res is not None:         # the element edges: whole rows and columns of the tensor mesh are split
                xs, ys = np.unique(np.round(res.mesh.p[0], 6)), np.unique(np.round(res.mesh.p[1], 6))
                for x in xs[(xs >= ext[3]) & (xs <= ext[2])]:
                    ax.axhline(x, color="k", lw=0.2, alpha=0.35)
                for y in ys[(ys >= ext[0]) & (ys <= ext[1])]:
                    ax.axvline(y, color="k", lw=0.2, alpha=0.35)
            ax.set_title(f"{name}, {title}", fontsize=10)
            ax.set_xlabel("lateral y (mm)")
            ax.set_ylabel("axial x (mm)")
        fig.colorbar(im, ax=axes[i], shrink=0.8, label=name)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
