"""R_P_sigma with its lambda_bar read from the data (the default) against the paper's fixed plane-stress
lambda_bar (``regularizer_options={"lambda_bar": 2}``), same pairs, same error metric.

The pairs: a soft plane-strain disk under the paper's probe (the figure's), then ten inclusions drawn after the
rule was fixed (3-15 MHz, 0.2-6 % compression, radius 3-8 mm, 15-30 dB; seven in plane strain, three in plane
stress).  Per pair: the strain ratio read (where it was solved again in plane strain), the
total strain error, e_xx and u_y errors, CPU time.  The figure (``--figure PATH``): e_yy and e_xy of the first
pair, truth / fixed / default, on one colour scale per row.

Usage: ``python benchmarks/plane_strain_model.py [--figure docs/plane_strain_model.png]`` (about 1 min).
"""
from __future__ import annotations

import argparse
import re
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import forward.fields as F  # noqa: E402
from benchmarks.robustness import Case, errors, make_data, roi_slices, truth  # noqa: E402
from forward.pairs import PROBES  # noqa: E402


#: (kind, model, compression %, radius mm, probe, size mm, SNR dB, top mm, seed) of each pair
PAIRS = (("soft", "plane-strain", 4, 5.0, "paper", (35, 30), 25, 2.5, 2),
         ("stiff", "plane-strain", 2, 6.0, "L12", (30, 30), 25, 5.0, 101),
         ("soft", "plane-strain", 3, 5.0, "L7", (30, 30), 20, 5.0, 102),
         ("stiff", "plane-strain", 1, 4.0, "L3", (40, 40), 25, 5.0, 103),
         ("soft", "plane-strain", 0.5, 3.0, "paper", (30, 30), 20, 5.0, 104),
         ("stiff", "plane-strain", 6, 5.0, "L7", (30, 30), 25, 5.0, 107),
         ("soft", "plane-strain", 0.2, 5.0, "L12", (30, 30), 25, 5.0, 108),
         ("stiff", "plane-strain", 3, 8.0, "L7", (35, 35), 15, 3.0, 109),
         ("stiff", "plane-stress", 2, 5.0, "L15", (20, 20), 30, 8.0, 105),
         ("soft", "plane-stress", 3, 6.0, "paper", (35, 30), 20, 5.0, 106),
         ("soft", "plane-stress", 1, 3.0, "L7", (30, 30), 25, 5.0, 110))


def _case(kind, model, percent, radius, probe, size, snr, top, seed):
    name = (f"{kind} {model.replace('-', ' ')} {percent:g} %, r {radius:g} mm, {PROBES[probe].f0_mhz:g} MHz"
            + (f", {snr:g} dB" if snr < 20 else ""))
    return Case(name, lambda: F.Inclusion(kind, model, percent / 100.0, radius_mm=radius), probe, size, snr,
                top_mm=top, seed=seed)


CASES = [_case(*p) for p in PAIRS]
VARIANTS = {"fixed lambda_bar 2": {"regularizer_options": {"lambda_bar": 2.0}}, "default": {}}


def run_case(case):
    import femreg

    data = make_data(case)
    out = {}
    for name, kw in VARIANTS.items():
        t = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin, **kw)
        sec = time.process_time() - t
        sl = roi_slices(res.shape, res.spacing)
        tr = truth(data, case, sl)
        e = errors(res.on_grid(), tr, sl, PROBES[case.probe].wavelength_mm)
        ratio = re.findall(r"strain ratio ([0-9.]+)", res.message)
        out[name] = dict(res=res, e=e, seconds=sec, resolved=bool(ratio), ratio=ratio[0] if ratio else "",
                         success=res.success)
    return data, out


def figure(path, case, data, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = out["default"]["res"]
    sl = roi_slices(res.shape, res.spacing)
    tr = truth(data, case, sl)
    x0, y0 = data.origin
    dx, dy = data.spacing
    ext = (y0 + sl[1].start * dy, y0 + (sl[1].stop - 1) * dy, x0 + (sl[0].stop - 1) * dx, x0 + sl[0].start * dx)
    fig, axes = plt.subplots(2, 3, figsize=(11.5, 7.6), constrained_layout=True)
    for row, comp in enumerate(("eyy", "exy")):
        t = 100 * tr[comp]
        lo, hi = np.percentile(t, [1, 99])
        pad = 0.15 * (hi - lo)
        panels = [("truth", t)] + [(f"{name}: {100 * out[name]['e']['e']:.1f} %",
                                    100 * np.asarray(out[name]["res"].on_grid()[comp])[sl]) for name in VARIANTS]
        for ax, (title, img) in zip(axes[row], panels):
            im = ax.imshow(img, extent=ext, aspect="equal", cmap="viridis" if comp == "eyy" else "RdBu_r",
                           vmin=lo - pad, vmax=hi + pad)
            ax.set_title(title, fontsize=10)
            ax.set_xlabel("lateral y (mm)")
            ax.set_ylabel("axial x (mm)")
        fig.colorbar(im, ax=axes[row].tolist(), shrink=0.9,
                     label=("lateral strain $\\varepsilon_{yy}$" if comp == "eyy" else
                            "shear strain $\\varepsilon_{xy}$") + " (%)")
    fig.suptitle(f"{case.name}: R_P_sigma with lambda_bar 2 against the data's (titles: total strain error)",
                 fontsize=11)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--figure", help="PNG of e_yy and e_xy of the first pair")
    a = ap.parse_args(argv)
    print("| pair | ratio read | solved in plane strain | total strain error % (fixed -> default) | e_xx % | "
          "u_y % | CPU s |")
    print("|---|---|---|---|---|---|---|")
    for k, case in enumerate(CASES):
        data, out = run_case(case)
        f, d = out["fixed lambda_bar 2"], out["default"]
        print(f"| {case.name} | {d['ratio'] or '-'} | {'yes' if d['resolved'] else 'no'} | "
              f"{100 * f['e']['e']:.2f} -> {100 * d['e']['e']:.2f} | {100 * f['e']['exx']:.2f} -> "
              f"{100 * d['e']['exx']:.2f} | {100 * f['e']['uy']:.2f} -> {100 * d['e']['uy']:.2f} | "
              f"{f['seconds']:.2f} -> {d['seconds']:.2f} |" + ("" if f["success"] and d["success"] else " FAILED |"),
              flush=True)
        if k == 0 and a.figure:
            figure(a.figure, case, data, out)


if __name__ == "__main__":
    main()
