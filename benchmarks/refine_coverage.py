"""What the unrefined solve says before the default refinement splits: fraction of rows / columns marked, median
and spread of the element NCC, the marking's largest jump over the cut, against the refined minus unrefined total
strain error (docs/robustness.md "Heterogeneous tissue", the table of :data:`femreg.refine.NOISE_COVERAGE`).

Cases: heterogeneous tissue with an independent speckle mixed into the moving frame (weights sqrt(1 - rho^2) and
rho; out-of-plane decorrelation), the heterogeneous 10 dB and 5 % cases, the 10 dB soft inclusion, two inclusions,
a shear band and in vivo seq304 frames 1 -> 2 (``--set choose``, the pairs the test was chosen on); pairs drawn
afterwards (``--set fresh``, with in vivo consecutive pairs); every pair of the robustness, heterogeneous,
inclusion and shear-band benchmarks (``--set all``).  Each pair: ``femreg.register`` defaults and ``refine=None``.
The numbers of the unrefined solve are read inside :func:`femreg.refine.refine_passes` (wrapped here), before its
own tests decide.  In vivo rows need ``../shared/data/invivo_rf`` (no truth: error columns empty).

Run: ``python benchmarks/refine_coverage.py [--set choose|fresh|all]`` (prints one JSON line per pair, then a
table; ``choose`` about 2 min, ``all`` about 5 min on one core).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import femreg  # noqa: E402
import femreg.refine as FR  # noqa: E402
from benchmarks import heterogeneous as H  # noqa: E402
from benchmarks import inclusion_sizes as I  # noqa: E402
from benchmarks import robustness as R  # noqa: E402
from benchmarks import shear_bands as S  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import PROBES, make_pair  # noqa: E402
from forward.tissue import RandomTissue  # noqa: E402

INVIVO = ROOT.parent / "shared" / "data" / "invivo_rf"
_seen = {}
_refine_passes = FR.refine_passes


def _measured(sol, opts, solve_on, spacing, origin):
    """refine_passes, recording the unrefined solve's numbers first."""
    from femreg.repair import element_ncc

    q = np.asarray(element_ncc(sol.data, sol.u, sol.mesh.t.shape[1]), float)
    q = q[np.isfinite(q)]
    _, _, _, (rs, cs) = FR.mark(sol.mesh, sol.u, opts, data=sol.data, scores=True)
    _seen.update(rows=float(np.mean(rs > 1)), cols=float(np.mean(cs > 1)),
                 coverage=FR.marked_coverage((rs, cs)), q_med=float(np.median(q)),
                 spread=FR.ncc_spread(q),
                 top=float(max(rs.max(initial=0.0), cs.max(initial=0.0))))
    _seen["uneven"] = _seen["spread"] / max(1e-9, 1.0 - _seen["q_med"])
    return _refine_passes(sol, opts, solve_on, spacing, origin)


def _pair(name, ref, mov, spacing, origin, truth=None, sl=None, lam=None) -> dict:
    _seen.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = femreg.register(ref, mov, spacing=spacing, origin=origin)
        row = dict(case=name, **_seen)
        rec = getattr(res, "refinement", None)
        row["split"] = bool(rec is not None and rec.passes)
        row["note"] = getattr(rec, "note", None)
        if truth is not None:
            off = femreg.register(ref, mov, spacing=spacing, origin=origin, refine=None)
            row["e_default"] = 100 * R.errors(res.on_grid(), truth, sl, lam)["e"]
            row["e_unrefined"] = 100 * R.errors(off.on_grid(), truth, sl, lam)["e"]
    print(json.dumps(row), flush=True)
    return row


def case_row(case) -> dict:
    data = R.make_data(case)
    sl = R.roi_slices(data.ref.shape, data.spacing)
    return _pair(case.name, data.ref, data.mov, data.spacing, data.origin, R.truth(data, case, sl), sl,
                 PROBES[case.probe].wavelength_mm)


def mixed_row(name, probe, size, seed, rho, sigma=0.7, level=0.01, snr=25.0) -> dict:
    """Heterogeneous tissue (plane stress) whose moving frame is mixed with an independent speckle frame."""
    f = RandomTissue(seed, level, "plane-stress", sigma=sigma, corr_mm=2.0)
    p = make_pair(f, probe, size, snr_db=snr, seed=seed, top_mm=3.0)
    q = make_pair(F.compression(0.0), probe, size, snr_db=None, seed=seed + 100, top_mm=3.0)
    mov = np.sqrt(1 - rho ** 2) * p.mov + rho * q.ref * np.std(p.mov) / np.std(q.ref)
    sl = R.roi_slices(p.ref.shape, p.spacing)
    t = R.truth(p, None, sl)                 # the mixed moving frame moves as p's field
    return _pair(name, p.ref, mov, p.spacing, p.origin, t, sl, PROBES[probe].wavelength_mm)


def invivo_row(seq, a, b):
    if not (INVIVO / seq).is_dir():
        return None
    spec = importlib.util.spec_from_file_location("demo07_invivo", ROOT / "demos" / "07_invivo.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    frames, spacing, origin = demo.load_sequence(INVIVO / seq)
    return _pair(f"{seq} {a} -> {b}", frames[a - 1], frames[b - 1], spacing, origin)


def _named(cases, name):
    return next(c for c in cases if c.name == name)


def run(which: str) -> list:
    FR.refine_passes = _measured
    rows = []
    try:
        if which == "choose":
            for probe, size, seed in (("L7", (30.0, 30.0), 31), ("paper", (40.0, 30.0), 32)):
                for rho in (0.0, 0.35, 0.5):
                    rows.append(mixed_row(f"rho {rho} {probe}", probe, size, seed, rho))
            for cases, name in ((H.CASES, "tissue1-pstress2_L7_10dB"), (H.CASES, "tissue0.5-pstress5_paper"),
                                (R.CASES, "soft-pstress4_L7"), (I.CASES, "r3_1pc_paper"), (I.CASES, "r1.5_1pc_L7"),
                                (S.CASES, "band1_s0.15_d15_L7")):
                rows.append(case_row(_named(cases, name)))
            rows.append(invivo_row("seq304", 1, 2))
        elif which == "fresh":
            rows.append(mixed_row("rho 0.4 L12 seed 41", "L12", (25.0, 25.0), 41, 0.4))
            rows.append(mixed_row("rho 0.5 L7 seed 43", "L7", (30.0, 30.0), 43, 0.5))
            rows.append(case_row(R.Case("tissue1-pstrain1_L3_15dB_s44", H._tissue(44, 0.01, "plane-strain", 1.0, 3.0),
                                        "L3", (40, 40), 15)))
            rows.append(case_row(R.Case("tissue0.7-pstress2_L7_12dB_s45",
                                        H._tissue(45, 0.02, "plane-stress", 0.7, 2.0), "L7", (30, 30), 12)))
            rows.append(mixed_row("rho 0.3 paper seed 46", "paper", (40.0, 30.0), 46, 0.3))
            rows.append(case_row(R.Case("tissue0.7-pstress3_L12_20dB_s47",
                                        H._tissue(47, 0.03, "plane-stress", 0.7, 2.0), "L12", (25, 25), 20,
                                        top_mm=5.0)))
            rows.append(case_row(R.Case("soft-pstress2_L12_10dB_s48", lambda: F.Inclusion("soft", "plane-stress", 0.02),
                                        "L12", (25, 25), 10, top_mm=7.5, seed=48)))
            for seq, a, b in (("seq304", 1, 2), ("seq304", 2, 3), ("seq304", 3, 4), ("seq304", 4, 5),
                              ("seq304", 5, 6), ("seq299", 1, 2), ("seq299", 3, 4), ("seq299", 4, 5), ("seq299", 5, 6)):
                rows.append(invivo_row(seq, a, b))
        else:
            for cases in (R.CASES, H.CASES, I.CASES, S.CASES):
                rows += [case_row(c) for c in cases if not c.sequence]
    finally:
        FR.refine_passes = _refine_passes
    return [r for r in rows if r is not None]


def table(rows) -> str:
    lines = ["| pair | rows / columns marked | coverage | median NCC | spread | spread / (1 - median) | top | split "
             "| default - unrefined (points) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d = (f"{r['e_default'] - r['e_unrefined']:+.2f} ({r['e_default']:.2f} / {r['e_unrefined']:.2f} %)"
             if "e_default" in r else "")
        if "coverage" not in r:
            lines.append(f"| {r['case']} | not refined (peak hopping or nothing to do) | | | | | | no | {d} |")
            continue
        lines.append(f"| {r['case']} | {r['rows']:.2f} / {r['cols']:.2f} | {r['coverage']:.2f} | {r['q_med']:.3f} "
                     f"| {r['spread']:.3f} | {r['uneven']:.2f} | {r['top']:.1f} | {'yes' if r['split'] else 'no'} "
                     f"| {d} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", default="choose", choices=("choose", "fresh", "all"))
    args = ap.parse_args(argv)
    print(table(run(args.set)))


if __name__ == "__main__":
    main()
