"""Demo 06: the paper's simulation study, end to end
=================================================

This demo shows how femreg reproduces the paper's results on simulated data:

1. **data**: the six simulated RF sequences (3D model with a hard / medium / no / soft inclusion, plane strain
   and plane stress with the hard one), 20 frames each, made once and cached (``forward.get_sequence``);
2. **alpha selection** (paper appendix "Algorithmic Parameter Justification"): register frame 1 to frame 7 of
   the four 3D sequences for alpha on a log grid 1e-6 ... 1e6, refine around the optimum, and pick per
   regulariser the alpha minimising the total strain error averaged over the inclusions,

   .. math:: \\alpha^* = \\arg\\min_\\alpha \\tfrac14 \\sum_{I \\in \\{HI, mHI, HOM, SI\\}}
             \\frac{\\|\\varepsilon^t - \\varepsilon^m_\\alpha\\|}{\\|\\varepsilon^t\\|};

3. **single frame** 1 -> 7 of all six data sets, **dual frame** 1 -> 3 / 1 -> 7 / 1 -> 10 and **accumulated**
   1 -> 20 (eq:IR, ``femreg.track``) of the 3D sequences, with the four regularisers R_eps, R_eps_i, R_P_eps and
   R_P_sigma at their selected alphas;
4. **report**: ``out/06_study/report.md`` with every femreg number beside the paper's, the ranking of the
   regularisers compared with the paper's, the targets, diagnostics, and the figures (alpha curves, error vs
   frame, displacement and strain images beside the truth).

Each registration is written to ``out/06_study/cases/`` as it finishes; running the demo again resumes.
``--quick``: 3D HI only, coarse alpha grid, accumulation to frame 7 (about 3 min on 2 cores with the data
cached), into out/06_study_quick/.  The full study: about 20 min of registrations plus about 5 min to simulate
the data sets the first time.
The selected alphas are written to ``alphas.json`` in the output folder (same format as femreg's shipped
defaults, femreg/data/default_alphas.json).  The study is the ``paperstudy`` package (it needs both femreg and
forward); ``femreg study`` runs the same code.
"""
import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from paperstudy import run_study  # noqa: E402

# The study runs on Dask worker processes, started by spawn, which import this script: keep the work
# under the main guard.
if __name__ == "__main__":
    ap = argparse.ArgumentParser(description="the paper's simulation study (report with femreg vs paper tables)")
    ap.add_argument("--quick", action="store_true", help="3D HI only, coarse alpha grid, 7 frames")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    args = ap.parse_args()

    # ## Run (resumes whatever an earlier run of this demo finished)
    out = Path("out") / ("06_study_quick" if args.quick else "06_study")  # relative to the working directory
    t0 = time.perf_counter()
    res = run_study(out, quick=args.quick, jobs=args.jobs, resume=True)

    # ## Headline: R_P_sigma on the 3D hard inclusion, femreg vs paper
    print(f"\nreport: {res.report}  ({time.perf_counter() - t0:.0f} s, {res.n_computed} cases computed)")
    print("selected alphas: " + ", ".join(f"{r} {a:.4g}" for r, a in res.alphas.items()))
    for (table, dataset), rows in sorted(res.tables.items()):
        if dataset != "3d-HI":
            continue
        line = ", ".join(f"{r} {row['e']:.1f}%" for r, row in rows.items())
        print(f"{table:12s} {dataset}: total strain error {line}")
