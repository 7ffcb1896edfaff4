"""The femreg rows of benchmarks/inversion.py (the default path: cached registration -> ``femreg.invert`` defaults)
with module constants of :mod:`femreg.inversion` set, for studies of the debiasing options (TV_REWEIGHT_STEPS,
TV_BREGMAN, TV_BREGMAN_FRACTION, TV_BREGMAN_START; TV_REFIT and its TV_REFIT_* constants; docs/inversion.md,
"Contrast-preserving TV" and "Region debias refit").

Same registrations (``$FEMREG_CACHE/bench_inversion/<key>``, which must hold every case: nothing is registered here),
the same contrast, ring, background CV and calibration as benchmarks/inversion.py; no exact, NCC or 1/SR rows.

Usage: ``python benchmarks/inversion_debias_study.py OUT.json [CONST=VALUE ...] [--sets main,held-out,...]``, then
``python benchmarks/inversion_debias_study.py --summary A.json B.json ...`` for the per-set counts.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

SETS = ("main", "held-out", "fresh", "fresh2", "fresh3", "fresh4")


def run(out, settings, sets):
    import femreg
    import femreg.inversion as inversion
    import inversion as bench

    for k, v in settings.items():
        setattr(inversion, k, v)
    folder = bench.cache_folder()
    rows = []
    for name in sets:
        for (m, c, pr, snr, r, lev, seed) in bench.SETS[name]:
            case = bench.case_name(m, c, pr, snr, r, lev, seed)
            path = folder / f"{case}.npz"
            if not path.exists():
                raise SystemExit(f"{path}: not registered (run benchmarks/inversion.py --set {name} first)")
            reg = femreg.load_result(path)
            field = bench.truth_field(m, c, lev, r)
            t = time.perf_counter()
            inv = femreg.invert(reg)
            dt = time.perf_counter() - t
            est, cv = bench.sampled_contrast(inv.shear_modulus, field.centre, field.radius_mm)
            ring = bench.ring_coverage(inv.shear_modulus, field.centre, field.radius_mm)
            _, _, z = bench.calibration(inv, field, c)
            rows.append(dict(set=name, case=case, contrast=c, estimate=est, ratio=est / c, cv=cv, ring=ring,
                             success=bool(inv.success), beta=inv.beta, z=z, seconds=dt, misfit=inv.misfit,
                             rule=inv.beta_rule, uncertainty_calibrated=inv.uncertainty_calibrated))
            print(f"{name} {case}: ratio {est / c:.3f}, CV {100 * cv:.0f} %, beta {inv.beta:.3g}"
                  f"{'' if inv.success else ', flagged'}", flush=True)
    Path(out).write_text(json.dumps(rows))


def summary(paths):
    """Per set: in the band (0.85-1.15, unflagged, measurable ring) / cases, CV <= 15 %, wrong side, calibration,
    results with ``uncertainty_calibrated`` False (all cases)."""
    for p in paths:
        rows = json.loads(Path(p).read_text())
        print(f"**{p}**")
        tot = [0, 0, 0, 0]
        for name in dict.fromkeys(r["set"] for r in rows):
            rs = [r for r in rows if r["set"] == name and r["ring"] >= 0.5]
            band = sum(r["success"] and 0.85 <= r["ratio"] <= 1.15 for r in rs)
            cv = sum(r["cv"] <= 0.15 for r in rs)
            wrong = sum(r["success"] and (r["estimate"] - 1) * (r["contrast"] - 1) < 0
                        for r in rows if r["set"] == name)
            z = np.concatenate([np.asarray(r["z"], float) for r in rs] + [np.zeros(0)])
            uncal = sum(r.get("uncertainty_calibrated") is False for r in rows if r["set"] == name)
            print(f"- {name}: {band}/{len(rs)} in the band, CV <= 15 % {cv}/{len(rs)}, wrong side {wrong}, "
                  f"within +-1 sigma {100 * np.mean(z <= 1):.1f} %, uncertainty not calibrated {uncal}")
            tot = [tot[0] + band, tot[1] + len(rs), tot[2] + cv, tot[3] + wrong]
        print(f"- total: {tot[0]}/{tot[1]} in the band, CV <= 15 % {tot[2]}/{tot[1]}, wrong side {tot[3]}, "
              f"{sum(r['seconds'] for r in rows):.0f} s")


if __name__ == "__main__":
    args = sys.argv[1:]
    if args and args[0] == "--summary":
        summary(args[1:])
    else:
        sets = SETS
        settings = {}
        for a in args[1:]:
            if a.startswith("--sets="):
                sets = tuple(a.split("=", 1)[1].split(","))
            else:
                k, v = a.split("=", 1)
                settings[k] = json.loads(v)
        run(args[0], settings, sets)
