"""``alpha="auto"`` out of sample: the robustness benchmark's pairs, which no rule of :mod:`femreg.autoalpha` was
chosen on.

For every two-frame case of ``benchmarks/robustness.py`` and every regulariser, :func:`femreg.autoalpha.choose_alpha`
runs its grid (the default alpha x 10^(-1.5 ... 1.5), half decades) with ``keep_results=True``; every grid result is
scored with the benchmark's metric (total strain error over the ROI against the exact truth), so the benchmark knows
the truth-best alpha of the same grid.  Printed per regulariser: how often the automatic alpha's error is within 15 %
of the best one's, the median and worst ratio, and the same for the fixed default alpha (the grid centre).

    python benchmarks/autoalpha.py [--seed 7] [--cases comp,incl] [--out out/autoalpha]
    python benchmarks/autoalpha.py --paper-seed 1     # the paper's six data sets, another realisation

``--paper-seed S``: instead, the paper's six simulated data sets (``forward.get_sequence(..., seed=S)``, frames
1 -> 7, 2 mm mesh, errors over the FE mesh against the exact truth, as in docs/study_report.md); seed 0 is the one
the study (and the rule's design) used.

Writes ``<out>/autoalpha.csv`` (one row per case x regulariser, the whole error curve) and ``<out>/autoalpha.md``.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

REGULARIZERS = ("strain", "strain-incompressible", "momentum-strain", "momentum-stress")
LABEL = {"strain": "R_eps", "strain-incompressible": "R_eps_i", "momentum-strain": "R_P_eps",
         "momentum-stress": "R_P_sigma"}
WITHIN = 1.15


def write_row(fh, writer, row: dict):
    """Append ``row`` to the open CSV ``fh`` (lists as JSON) and flush it, so that an interrupted run keeps its
    rows; ``writer`` None writes the header first.  Returns the writer to pass next time."""
    flat = {k: (json.dumps(v) if isinstance(v, list) else v) for k, v in row.items()}
    if writer is None:
        writer = csv.DictWriter(fh, fieldnames=list(flat))
        writer.writeheader()
    writer.writerow(flat)
    fh.flush()
    return writer


def run_case(case):
    """Rows (one per regulariser) of one benchmark case."""
    import robustness as RB
    from femreg.autoalpha import choose_alpha

    data = RB.make_data(case)
    sl = RB.roi_slices(data.ref.shape, data.spacing)
    t = RB.truth(data, case, sl)
    lam = RB.PROBES[case.probe].wavelength_mm
    rows = []
    for reg in REGULARIZERS:
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ch = choose_alpha(data.ref, data.mov, keep_results=True, regularizer=reg, spacing=data.spacing,
                              origin=data.origin)
        dt = time.perf_counter() - t0
        e = np.array([RB.errors(r.on_grid(), t, sl, lam)["e"] for r in ch.results])
        rows.append(_row(case.name, reg, ch, e, dt))
    return rows


PAPER_SETS = (("3d", "HI"), ("plane-strain", "HI"), ("plane-stress", "HI"), ("3d", "SI"), ("3d", "HOM"),
              ("3d", "mHI"))


def run_paper_set(dim, inc, seed):
    """Rows (one per regulariser) of one of the paper's data sets, frames 1 -> 7, 2 mm mesh."""
    import forward
    from femreg.autoalpha import choose_alpha
    from femreg.metrics import field_errors

    s = forward.get_sequence(dim, inc, seed=seed)
    rows = []
    for reg in REGULARIZERS:
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ch = choose_alpha(s.frames[0], s.frames[6], keep_results=True, regularizer=reg, spacing=s.spacing,
                              origin=s.origin, element_size=2.0)
        dt = time.perf_counter() - t0
        e = np.array([field_errors(r, lambda p: s.true_displacement(6, p), lambda p: s.true_strain(6, p))["e"]
                      for r in ch.results])
        rows.append(_row(f"{dim}-{inc}", reg, ch, e, dt))
    return rows


def _row(name, reg, ch, e, dt):
    ok = [bool(r.success) for r in ch.results]
    k = int(np.argmin(np.abs(np.log(ch.alphas / ch.alpha))))
    good = np.where(ok, e, np.inf)
    best = int(np.argmin(good)) if np.isfinite(good).any() else int(np.argmin(e))
    mid = len(ch.alphas) // 2
    return dict(case=name, regularizer=LABEL[reg], auto_alpha=float(ch.alpha), best_alpha=float(ch.alphas[best]),
                e_auto=float(e[k]), e_best=float(e[best]), e_default=float(e[mid]), ratio=float(e[k] / e[best]),
                ratio_default=float(e[mid] / e[best]), success=ok, curve=[float(x) for x in e],
                alphas=[float(a) for a in ch.alphas], time_s=dt)


def summary(rows) -> str:
    L = ["| regulariser | auto within 15 % | median / max ratio | default alpha within 15 % | median / max ratio |",
         "|---|---|---|---|---|"]
    groups = [(lab, [r for r in rows if r["regularizer"] == lab]) for lab in LABEL.values()] + [("all", rows)]
    for lab, rs in groups:
        if not rs:
            continue
        a = np.array([r["ratio"] for r in rs])
        d = np.array([r["ratio_default"] for r in rs])
        L.append(f"| {lab} | {int(np.sum(a <= WITHIN))}/{a.size} | {np.median(a):.2f} / {a.max():.2f} | "
                 f"{int(np.sum(d <= WITHIN))}/{d.size} | {np.median(d):.2f} / {d.max():.2f} |")
    L += ["", "| case | regulariser | auto alpha | e at auto | best alpha | e at best | ratio | default: e |",
          "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['case']} | {r['regularizer']} | {r['auto_alpha']:.3g} | {100 * r['e_auto']:.2f} % | "
                 f"{r['best_alpha']:.3g} | {100 * r['e_best']:.2f} % | {r['ratio']:.2f} | "
                 f"{100 * r['e_default']:.2f} % |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--seed", type=int, default=0, help="added to every case's seed (other realisations)")
    ap.add_argument("--paper-seed", type=int, default=None,
                    help="run the paper's six data sets with this realisation seed instead of the robustness pairs")
    ap.add_argument("--out", default="out/autoalpha")
    a = ap.parse_args(argv)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import robustness as RB
    from tqdm import tqdm

    if a.paper_seed is not None:
        jobs = [(lambda d=d, i=i: run_paper_set(d, i, a.paper_seed), f"{d}-{i}") for d, i in PAPER_SETS]
        label = f"the paper's six data sets, realisation seed {a.paper_seed}"
    else:
        jobs = None
    cases = [c for c in RB.CASES if not c.sequence]
    if a.cases:
        words = [w for w in a.cases.split(",") if w]
        cases = [c for c in cases if any(w in c.name for w in words)]
    if a.seed:
        cases = [dataclasses.replace(c, seed=c.seed + a.seed) for c in cases]
    if jobs is None:
        jobs = [(lambda c=c: run_case(c), c.name) for c in cases]
        label = f"{len(cases)} robustness pairs, seed offset {a.seed}"
    if not jobs:
        print("no case selected", file=sys.stderr)
        return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    t0 = time.perf_counter()
    with open(out / "autoalpha.csv", "w", newline="") as fh:     # row by row: an interrupted run keeps its rows
        w = None
        for job, _name in tqdm(jobs, desc="cases", file=sys.stderr):
            for r in job():
                rows.append(r)
                w = write_row(fh, w, r)
    md = summary(rows) + f"\n{label} x {len(REGULARIZERS)} regularisers, {time.perf_counter() - t0:.0f} s\n"
    (out / "autoalpha.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
