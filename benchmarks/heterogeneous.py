"""Heterogeneous tissue: registration and modulus inversion where the stiffness varies everywhere.

Every other benchmark images a uniform block or one disk in a background; real tissue is neither.  Here the truth
is :class:`forward.tissue.RandomTissue`: a smooth random modulus (log E of standard deviation ``sigma``,
correlation length 1.5-3 mm), plane strain or plane stress, compressed 0.3-5 %, imaged by 3-15 MHz probes at
10-30 dB.  None of femreg's defaults was chosen on these cases.

Registration (default): :func:`benchmarks.robustness.run` on these cases, same ROI and metric (total strain
error, ux / uy errors), femreg's R_P_sigma and R_eps rows beside NCC block matching, SimpleITK's B-spline and
scikit-image's TV-L1 optical flow, one picture per case; ``--refine none`` registers femreg's rows unrefined.

Inversion (``--invert``): each pair registered with the defaults and inverted with ``femreg.invert(res)``;
scored at the inversion's element centres inside the ROI against the true modulus, both divided by their
median (the inversion is relative): the Pearson correlation of log mu with the true log E, the RMS of
log(mu / E), the fraction of elements within 0.85-1.15 of the truth, the fraction whose true log E lies within
+-1 sigma of the uncertainty, the flags, and whether the result calls its uncertainty calibrated
(``uncertainty_calibrated``).  Rows: ``femreg`` (registered), ``exact`` (the forward model's own
displacement on the same mesh: the floor) and ``1/strain`` (the axial strain's inverse, what users read as
stiffness, from the same registration).

Run: ``python benchmarks/heterogeneous.py [--out DIR] [--cases WORDS] [--methods WORDS] [--refine none]
[--invert [--regularization tikhonov]] [--check]`` (registration rows about 5 min on 2 cores; ``--invert`` about
2 min; ``--check``: the four :data:`CHECK` pairs instead of :data:`CASES`).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import robustness as R  # noqa: E402
from forward.tissue import RandomTissue  # noqa: E402


def _tissue(seed, level, model, sigma=0.5, corr=2.0):
    return lambda: RandomTissue(seed, level, model, sigma=sigma, corr_mm=corr)


#: name: sigma of log E, model, compression, probe, (depth, width) mm, SNR dB; seeds differ case to case.
CASES = [
    R.Case("tissue0.5-pstress1_paper", _tissue(11, 0.01, "plane-stress", 0.5, 2.0), "paper", (40, 30), 20),
    R.Case("tissue0.5-pstrain3_L7", _tissue(12, 0.03, "plane-strain", 0.5, 2.0), "L7", (30, 30), 25),
    R.Case("tissue1-pstress1_L12", _tissue(13, 0.01, "plane-stress", 1.0, 1.5), "L12", (25, 25), 30, top_mm=5.0),
    R.Case("tissue1-pstrain1_L3", _tissue(14, 0.01, "plane-strain", 1.0, 3.0), "L3", (40, 40), 15),
    R.Case("tissue0.5-pstress0.3_L7", _tissue(15, 0.003, "plane-stress", 0.5, 2.0), "L7", (30, 30), 30),
    R.Case("tissue0.5-pstress5_paper", _tissue(16, 0.05, "plane-stress", 0.5, 2.5), "paper", (40, 30), 25),
    R.Case("tissue1-pstress2_L7_10dB", _tissue(17, 0.02, "plane-stress", 1.0, 2.0), "L7", (30, 30), 10,
           notes="SNR 10 dB"),
    R.Case("tissue0.7-pstrain1_L15", _tissue(18, 0.01, "plane-strain", 0.7, 1.5), "L15", (15, 15), 40,
           top_mm=10.0),
]

#: Four pairs drawn after the uncertainty's bias term (femreg.inversion.UNCALIBRATED_SPREAD) was chosen on CASES, to
#: check it (``--check``): other seeds, probes and sigmas.
CHECK = [
    R.Case("xtissue0.7-pstrain1_L7", _tissue(21, 0.01, "plane-strain", 0.7, 2.0), "L7", (30, 30), 20),
    R.Case("xtissue0.7-pstress2_L3", _tissue(22, 0.02, "plane-stress", 0.7, 2.5), "L3", (40, 40), 20),
    R.Case("xtissue0.5-pstrain1_paper", _tissue(23, 0.01, "plane-strain", 0.5, 2.0), "paper", (40, 30), 25),
    R.Case("xtissue1-pstress1_L12", _tissue(24, 0.01, "plane-stress", 1.0, 2.0), "L12", (25, 25), 25, top_mm=5.0),
]

METHODS = ["R_P_sigma", "R_eps", "NCC BM", "B-spline (SimpleITK)", "TV-L1 (skimage)"]


def invert_case(case, inv_kw=None):
    """Rows (femreg, exact, 1/strain) of the inversion metrics of one case (module docstring)."""
    import femreg

    data = R.make_data(case)
    field = data.field
    sl = R.roi_slices(data.ref.shape, data.spacing)
    x0, y0 = data.origin
    dx, dy = data.spacing
    roi = ((x0 + sl[0].start * dx, x0 + (sl[0].stop - 1) * dx), (y0 + sl[1].start * dy, y0 + (sl[1].stop - 1) * dy))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0 = time.process_time()
        res = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin)
        t_reg = time.process_time() - c0
        c0 = time.process_time()
        inv = femreg.invert(res, **(inv_kw or {}))
        t_inv = time.process_time() - c0
        p, t = inv.mesh.p, inv.mesh.t
        h = float(np.median(np.diff(np.unique(np.round(p[0], 6)))))
        region = ((float(p[0].min()), float(p[0].max())), (float(p[1].min()), float(p[1].max())))
        hy = float(np.median(np.diff(np.unique(np.round(p[1], 6)))))
        ex = femreg.invert(field.displacement, region=region, element_size=(h, hy), model=inv.model)
    rows = []
    for name, r in (("femreg", inv), ("exact", ex)):
        rows.append(dict(case=case.name, row=name, **_score(r.mesh, r.mu, getattr(r, "uncertainty", None),
                                                           field, roi), success=r.success,
                         flags="; ".join(r.flags)[:80], model=r.model, n_el=r.mesh.t.shape[1],
                         uncertainty_calibrated=r.uncertainty_calibrated,
                         unsupported_area=r.unsupported_area, refit_skipped="not applied" in r.beta_rule,
                         notes="; ".join(r.notes)[:120],
                         cpu_s=t_inv if name == "femreg" else float("nan")))
    # what users otherwise read as stiffness: 1 / |axial strain| of the same registration, per element
    centres = inv.mesh.p[:, inv.mesh.t].mean(axis=1).T
    exx = res.strain(centres, "element")[:, 0]
    stiff = 1.0 / np.maximum(np.abs(exx), 1e-6)
    rows.append(dict(case=case.name, row="1/strain", **_score(inv.mesh, stiff, None, field, roi),
                     success=True, flags="", model="", n_el=inv.mesh.t.shape[1], cpu_s=float("nan"),
                     uncertainty_calibrated=None))
    for r in rows:
        r["reg_cpu_s"] = t_reg
    return rows


def _score(mesh, mu, sigma, field, roi) -> dict:
    c = mesh.p[:, mesh.t].mean(axis=1).T
    inside = ((c[:, 0] >= roi[0][0]) & (c[:, 0] <= roi[0][1]) & (c[:, 1] >= roi[1][0]) & (c[:, 1] <= roi[1][1]))
    mu = np.asarray(mu, float)
    ok = inside & np.isfinite(mu) & (mu > 0)
    if ok.sum() < 10:
        return dict(corr=float("nan"), rms_log=float("nan"), in_band=float("nan"), calibrated=float("nan"))
    lt = np.log(field.modulus(c[ok]))
    le = np.log(mu[ok])
    lt, le = lt - np.median(lt), le - np.median(le)
    out = dict(corr=float(np.corrcoef(lt, le)[0, 1]), rms_log=float(np.sqrt(np.mean((le - lt) ** 2))),
               in_band=float(np.mean(np.abs(le - lt) <= math.log(1.15))))
    if sigma is not None:
        s = np.asarray(sigma, float)[ok]
        good = np.isfinite(s) & (s > 0)
        out["calibrated"] = float(np.mean(np.abs(le - lt)[good] <= s[good])) if good.any() else float("nan")
    else:
        out["calibrated"] = float("nan")
    return out


def invert_table(rows) -> str:
    lines = ["| case | row | corr(log mu, log E) | RMS log(mu/E) | within 0.85-1.15 | within +-1 sigma | success "
             "| uncertainty calibrated | model | elements | CPU s | flags |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cal = "" if not np.isfinite(r["calibrated"]) else f"{100 * r['calibrated']:.0f} %"
        cpu = "" if not np.isfinite(r["cpu_s"]) else f"{r['cpu_s']:.1f}"
        lines.append(f"| {r['case']} | {r['row']} | {r['corr']:.2f} | {r['rms_log']:.2f} | "
                     f"{100 * r['in_band']:.0f} % | {cal} | {r['success']} | "
                     f"{'' if r.get('uncertainty_calibrated') is None else r['uncertainty_calibrated']} | "
                     f"{r['model']} | {r['n_el']} | {cpu} | "
                     f"{r['flags']} |")
    by = {}
    for r in rows:
        by.setdefault(r["row"], []).append(r)
    lines.append("")
    for name, rs in by.items():
        cal = [r["calibrated"] for r in rs if np.isfinite(r["calibrated"])]
        lines.append(f"- {name}: median corr {np.median([r['corr'] for r in rs]):.2f} "
                     f"(min {min(r['corr'] for r in rs):.2f}), median RMS log {np.median([r['rms_log'] for r in rs]):.2f}, "
                     f"median within 15 % {100 * np.median([r['in_band'] for r in rs]):.0f} %"
                     + (f", pooled within +-1 sigma {100 * np.mean(cal):.0f} %" if cal else "")
                     + f", flagged {sum(not r['success'] for r in rs)}/{len(rs)}"
                     + (f", uncertainty_calibrated False {sum(r.get('uncertainty_calibrated') is False for r in rs)}"
                        f"/{len(rs)}" if any(r.get("uncertainty_calibrated") is not None for r in rs) else ""))
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "heterogeneous")
    ap.add_argument("--cases", default="", help="comma-separated words; a case runs when its name contains one")
    ap.add_argument("--methods", default="", help="comma-separated words selecting the registration methods")
    ap.add_argument("--refine", default=None, help="refine= of femreg's pairs: none, auto or a number")
    ap.add_argument("--invert", action="store_true", help="the inversion rows instead of the registration rows")
    ap.add_argument("--regularization", default=None, choices=("tv", "tikhonov"),
                    help="--invert: regularization= of femreg.invert (default: invert's own)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--check", action="store_true", help="the CHECK pairs instead of CASES")
    a = ap.parse_args(argv)
    cases = R.select_cases(CHECK if a.check else CASES, a.cases)
    if not cases:
        ap.error(f"no case matches {a.cases!r}; cases: {', '.join(c.name for c in CASES)}")
    a.out.mkdir(parents=True, exist_ok=True)
    if a.invert:
        rows = []
        for case in cases:
            rows += invert_case(case, {"regularization": a.regularization} if a.regularization else None)
            r = rows[-3]
            print(f"# {case.name}: femreg corr {r['corr']:.2f} RMS log {r['rms_log']:.2f} "
                  f"success {r['success']}", file=sys.stderr, flush=True)
        md = invert_table(rows)
        (a.out / "inversion.md").write_text(md)
        print(md)
        return 0
    if a.refine is not None:
        R.REFINE = R.parse_refine(a.refine)
    methods = R.select_methods(a.methods) if a.methods else METHODS
    R.run(cases, methods, a.out, progress=not a.no_progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
