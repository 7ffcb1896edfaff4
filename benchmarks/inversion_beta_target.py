"""The beta rule's target with the present ``femreg.invert`` defaults (reweighted TV and the region refit): per case
of a :mod:`benchmarks.inversion` set, the truth-best beta (the grid beta, 1 ... 1e-4 in half decades as in
benchmarks/inversion.py, whose fixed-beta inversion gives the contrast ratio closest to 1) and its ratio; the rule's
ratio comes from a JSON of benchmarks/inversion_debias_study.py on the same registrations.  "Within 15 %" as in
benchmarks/inversion.py: |ratio_rule / ratio_best - 1| <= 0.15, over the cases with a measurable ring.

Usage: ``FEMREG_CACHE=DIR python benchmarks/inversion_beta_target.py BEST.json --sets=held-out,fresh`` (the
registrations must be in the cache, as for the debias study; resumes a partial BEST.json), then
``python benchmarks/inversion_beta_target.py --summary RULE.json BEST.json``.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402


def run(out, sets):
    import femreg
    import femreg.inversion as inversion
    import inversion as bench

    out = Path(out)
    rows = json.loads(out.read_text()) if out.exists() else []
    done = {(r["set"], r["case"]) for r in rows}
    grid = tuple(inversion.BETA_GRID[0] * 10.0 ** (0.5 * np.arange(inversion.DOF_UP_STEPS, 0, -1))) + \
        tuple(inversion.BETA_GRID)
    for name, case, c, reg, field in bench.registered_cases(sets, skip=done):
        t = time.perf_counter()
        sweep = []
        for b in grid:
            fi = femreg.invert(reg, beta=float(b), uncertainty=False)
            ratio = bench.sampled_contrast(fi.shear_modulus, field.centre, field.radius_mm)[0] / c
            sweep.append((float(b), float(ratio), bool(fi.success)))
        best = min(sweep, key=lambda e: abs(np.log(e[1])))
        rows.append(dict(set=name, case=case, best_beta=best[0], best_ratio=best[1], sweep=sweep,
                         seconds=time.perf_counter() - t))
        print(f"{name} {case}: truth-best beta {best[0]:.3g} (ratio {best[1]:.3f})", flush=True)
        out.write_text(json.dumps(rows))


def summary(rule_path, best_path):
    rule = {(r["set"], r["case"]): r for r in json.loads(Path(rule_path).read_text())}
    best = json.loads(Path(best_path).read_text())
    tot = [0, 0]
    for name in dict.fromkeys(b["set"] for b in best):
        rows = [(rule[(b["set"], b["case"])], b) for b in best if b["set"] == name
                and (b["set"], b["case"]) in rule and rule[(b["set"], b["case"])]["ring"] >= 0.5]
        ok = [abs(r["ratio"] / b["best_ratio"] - 1.0) <= 0.15 for r, b in rows]
        print(f"- {name}: within 15 % of the truth-best beta's ratio {sum(ok)}/{len(ok)}")
        for (r, b), good in zip(rows, ok):
            if not good:
                print(f"  - {r['case']}: rule beta {r['beta']:.3g} ratio {r['ratio']:.3f}, truth-best beta "
                      f"{b['best_beta']:.3g} ratio {b['best_ratio']:.3f}")
        tot = [tot[0] + sum(ok), tot[1] + len(ok)]
    print(f"- total: {tot[0]}/{tot[1]}")


if __name__ == "__main__":
    args = sys.argv[1:]
    if args and args[0] == "--summary":
        summary(args[1], args[2])
    else:
        sets = ("held-out", "fresh", "fresh2", "main")
        for a in args[1:]:
            if a.startswith("--sets="):
                sets = tuple(a.split("=", 1)[1].split(","))
        run(args[0], sets)
