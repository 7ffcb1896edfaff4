"""Consistency checks of ``femreg.invert`` against silently wrong results: registrations with R_eps (``regularizer=
"strain"``) beside the default (R_P_sigma) rows of benchmarks/inversion.py.

Collect (``--collect``): every case of the sets asked (benchmarks/inversion.py's :data:`SETS`, plus ``reps``: the main
set's 16 pairs and 8 more pairs of seeds 1-4, registered with R_eps) is registered (cached as in
benchmarks/inversion.py), inverted with ``femreg.invert`` defaults (``model="auto"``; R_eps pairs also with
``model="plane-stress"`` and ``"plane-strain"``; no uncertainty: the flags do not depend on it) and the result saved
under ``$FEMREG_CACHE/inversion_consistency``, with a JSON row (contrast ratio to the truth, flags).
Summary (default): per set, the unflagged results outside 0.85-1.15 (silently wrong) and the flagged ones inside it
(false flags), from the saved rows.

Usage: ``python benchmarks/inversion_consistency.py --collect --set reps --set main ...`` then
``python benchmarks/inversion_consistency.py``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import femreg  # noqa: E402
import inversion as B  # noqa: E402
from forward.elasticity import cache_dir  # noqa: E402
from forward.pairs import make_pair  # noqa: E402

#: R_eps pairs beside the main set's: (model, contrast, probe, snr, radius, compression, seed), seeds 1-4.
REPS_EXTRA = tuple((m, c, pr, snr, 5.0, 0.01, seed)
                   for m in B.MODELS
                   for c, pr, snr, seed in ((4.0, "L7", 20.0, 1), (4.0, "paper", 25.0, 2), (2.0, "L12", 20.0, 3),
                                            (0.25, "L7", 25.0, 4)))
REPS = B.SETS["main"] + REPS_EXTRA


def out_folder():
    f = cache_dir() / "inversion_consistency"
    f.mkdir(parents=True, exist_ok=True)
    return f


def register_reps(case, field, probe, snr, seed):
    path = B.cache_folder() / f"strain_{case}.npz"
    if path.exists():
        return femreg.load_result(path)
    pair = make_pair(field, probe, B.SIZE, snr, seed, top_mm=B.TOP, name=case)
    res = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, regularizer="strain")
    res.save(path)
    return res


def collect(set_name):
    rows_path = out_folder() / f"rows_{set_name}.json"
    rows = json.loads(rows_path.read_text()) if rows_path.exists() else []
    done = {(r["case"], r["regularizer"], r["asked"]) for r in rows}
    specs = REPS if set_name == "reps" else B.SETS[set_name]
    for spec in specs:
        model, contrast, probe, snr, radius, level, seed = spec
        case = B.case_name(model, contrast, probe, snr, radius, level, seed)
        regname = "strain" if set_name == "reps" else "default"
        asked = ("auto", "plane-stress", "plane-strain") if regname == "strain" else ("auto",)
        if all((case, regname, a) in done for a in asked):
            continue
        field = B.truth_field(model, contrast, level, radius)
        t = time.perf_counter()
        reg = (register_reps(case, field, probe, snr, seed) if regname == "strain"
               else B.register(case, field, probe, snr, seed)[0])
        t_reg = time.perf_counter() - t
        for a in asked:
            t = time.perf_counter()
            inv = femreg.invert(reg, model=a, uncertainty=False)
            path = out_folder() / f"{regname}_{a}_{case}.npz"
            inv.save(path)
            c, cv = B.sampled_contrast(inv.shear_modulus, field.centre, field.radius_mm)
            ring = B.ring_coverage(inv.shear_modulus, field.centre, field.radius_mm)
            rows.append(dict(set=set_name, case=case, regularizer=regname, asked=a, model=model, contrast=contrast,
                             probe=probe, snr=snr, radius=radius, level=level, seed=seed, chosen=inv.model,
                             estimate=c, ratio=c / contrast, cv=cv, ring=ring, success=bool(inv.success),
                             flags="; ".join(inv.flags), strain_ratio=inv.strain_ratio, beta=inv.beta,
                             centre=list(map(float, field.centre)), R=float(field.radius_mm), file=path.name,
                             seconds=time.perf_counter() - t, reg_seconds=t_reg))
            print(f"{set_name} {case} {regname} {a}: {inv.model} ratio {c / contrast:.2f} success {inv.success} "
                  f"r {inv.strain_ratio:.3f} ({t_reg:.0f} s + {time.perf_counter() - t:.0f} s)", flush=True)
        rows_path.write_text(json.dumps(rows, default=float))
    return rows


def shortfall(row):
    """:func:`femreg.inversion._lateral_shortfall` of a saved result (the smallest quadrant shortfall of the model's
    lateral expansion against the data's), recomputed from its ``u_model`` so that rows saved before the check have
    it too."""
    from skfem import Basis, ElementVector

    from femreg.inversion import _element_strain, _elements, _lateral_shortfall, load_inversion

    inv = load_inversion(out_folder() / row["file"])
    basis = Basis(inv.mesh, ElementVector(_elements(inv.mesh)[0]), intorder=2)
    el, _ = _element_strain(basis, inv.u_model)
    return _lateral_shortfall(inv.strain_measured, el, inv.mesh, basis.dx.sum(axis=1), inv.model)[0]


def _band(r):
    return 0.85 <= r["ratio"] <= 1.15


def summary(sets, tol):
    """Per set and row kind: results, flagged before, in the band unflagged before, and what the shortfall flag
    (above ``tol``) adds: false flags (unflagged results in the band it flags) and flagged misses (unflagged results
    outside the band it flags); the benchmark's measurable-ring rule applies to the in-band count."""
    rows = []
    for s in sets:
        path = out_folder() / f"rows_{s}.json"
        if path.exists():
            rows += json.loads(path.read_text())
    lines = ["| set | rows | results | flagged before | in band before | in band after | false flags | flagged misses "
             "| misses left unflagged | largest shortfall of unflagged in-band results |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    detail = []
    for s in dict.fromkeys(r["set"] for r in rows):
        for kind in ("default auto", "strain auto", "strain plane-stress", "strain plane-strain"):
            reg, asked = kind.split()
            sel = [r for r in rows if r["set"] == s and r["regularizer"] == reg and r["asked"] == asked
                   and r.get("ring", 1.0) >= B.RING_MEASURABLE]
            if not sel:
                continue
            for r in sel:
                r["short"] = shortfall(r)
                r["new"] = r["short"] > tol
            ok = [r for r in sel if r["success"]]
            band = [r for r in ok if _band(r)]
            false = [r for r in band if r["new"]]
            caught = [r for r in ok if not _band(r) and r["new"]]
            left = [r for r in ok if not _band(r) and not r["new"]]
            big = max((r["short"] for r in band), default=np.nan)
            lines.append(f"| {s} | {kind} | {len(sel)} | {len(sel) - len(ok)} | {len(band)} | "
                         f"{len(band) - len(false)} | {len(false)} | {len(caught)} | {len(left)} | {big:+.3f} |")
            for r in sel:
                detail.append(f"{s} {kind} {r['case']}: ratio {r['ratio']:.2f}, success before {r['success']}, "
                              f"shortfall {r['short']:+.3f}{' FLAG' if r['new'] else ''}")
    return "\n".join(lines), "\n".join(detail)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--collect", action="store_true")
    ap.add_argument("--set", action="append", help="reps or a set of benchmarks/inversion.py")
    ap.add_argument("--tolerance", type=float, default=None, help="shortfall flagged (default the package's)")
    ap.add_argument("--detail", action="store_true", help="one line per result")
    a = ap.parse_args(argv)
    sets = a.set or ["reps", "main", "held-out", "fresh", "fresh2", "fresh3", "fresh4", "curves"]
    if a.collect:
        for s in sets:
            collect(s)
        return
    from femreg.inversion import MODEL_RATIO_TOLERANCE

    table, detail = summary(sets, MODEL_RATIO_TOLERANCE if a.tolerance is None else a.tolerance)
    print(table)
    if a.detail:
        print(detail)


if __name__ == "__main__":
    main()
