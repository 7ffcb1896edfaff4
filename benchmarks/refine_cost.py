"""Cost and effect of adaptive refinement (:mod:`femreg.refine`) on the robustness benchmark's pairs: R_P_sigma with
``refine=None`` and with ``refine=<spec>``, the same pairs, CPU time (``time.process_time``, the minimum over
``--repeats`` interleaved runs: the machine may be shared, wall time is not a measure there) and the total strain
error of :func:`benchmarks.robustness.errors`.

Per case: error (%) without -> with refinement (and the success flags where they differ), its difference (points),
CPU seconds of both and their ratio, the elements before -> after.  The summary line gives the largest error increase and the median and largest time
ratio: the gate for refinement as a default is no case worse by more than 0.3 points and no pair over 2x.
The sequence case is registered pair by pair as a plain pair (frame 0 -> 1) here: ``femreg.track`` does not refine.

Run: ``python benchmarks/refine_cost.py [--cases words] [--repeats 3]
[--refine auto|slip|norelax|nofine|nofill|fine:G|finealpha:F|deep|lowcut|lowcut:F|twopass|N] [--against norelax] [--seed 0]
[--out out/refine_cost]`` (``nofine``: the default without its finer marking,
:attr:`femreg.refine.Refinement.fine`; ``fine:G``: with its gate at G x the cut; ``--against``: also that
``refine=``, and the error change of ``--refine`` against it: the gate of a change to the default refinement).
A first registration of a small pair is run (and not timed) before the cases so that compiled kernels are ready.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.robustness import CASES, errors, make_data, roi_slices, truth  # noqa: E402
from forward.pairs import PROBES  # noqa: E402


def deep_refinement():
    """:data:`femreg.refine.DEEP_REFINEMENT` (what ``refine="auto"`` means): one pass splitting each marked row /
    column twice (to a quarter) down to 0.15 mm axially, with no element budget, and the local relaxation on that
    one solve (weight 0.02 on the unrefined cells beside the edges whose shear-traction jump stands out on the
    solve before the split, on a run of at least 20 mm); where a row / column stands out 4.6x the cut, the marking
    at a z-score of 1 and columns down to 0.4 mm (:attr:`femreg.refine.Refinement.fine`); a pass that relaxes
    solves to the registration's stopping rules at 0.4x its weight (:attr:`femreg.refine.Refinement.relax_full`)."""
    from femreg.refine import DEEP_REFINEMENT

    return DEEP_REFINEMENT


def _spec(name):
    from femreg.refine import SLIP_REFINEMENT, Refinement

    if name in ("none", "0"):
        return None
    if name == "slip":
        return SLIP_REFINEMENT
    if name == "norelax":           # the default refinement without its local relaxation
        return Refinement(relax=None)
    if name == "deep":
        return deep_refinement()
    if name.split(":")[0] == "lowcut":   # measured, not the default: DEEP_REFINEMENT marking at a z-score of 2
        import dataclasses as dc

        spec = dc.replace(deep_refinement(), threshold=2.0, min_size=(0.15, 0.3), relax_threshold=4.0,
                          feature_threshold=4.0)
        # "lowcut:F": its feature test at F x the (z-score 4) cut instead of 2.2
        return dc.replace(spec, feature=float(name.split(":")[1])) if ":" in name else spec
    if name == "nofinealpha":       # the default refinement at the unrefined weight on its finer passes too
        import dataclasses as dc

        return dc.replace(deep_refinement(), fine_alpha=None, fine_alpha_ncc=None)
    if name == "nofill":            # the default refinement without its core split (Refinement.fine_fill)
        import dataclasses as dc

        return dc.replace(deep_refinement(), fine_fill=0)
    if name == "nofine":            # the default refinement without its finer marking (Refinement.fine)
        import dataclasses as dc

        return dc.replace(deep_refinement(), fine=None)
    if name.split(":")[0] == "fine":    # "fine:G": the default refinement with its finer marking gated at G x the cut
        import dataclasses as dc

        return dc.replace(deep_refinement(), fine=float(name.split(":")[1]))
    if name.split(":")[0] == "finealpha":   # "finealpha:F": the default with fine_alpha=F on its finer passes
        import dataclasses as dc

        # "finealpha:F:N": F the smallest factor, reached at 1 - median element NCC = F * N (fine_alpha_ncc N)
        v = [float(x) for x in name.split(":")[1:]]
        return dc.replace(deep_refinement(), fine_alpha=v[0], fine_alpha_ncc=v[1] if len(v) > 1 else None)
    if name == "twopass":           # the two-pass refinement (the default before DEEP_REFINEMENT)
        return Refinement()
    return name if name == "auto" else int(name)


def _pair(case, data):
    if case.sequence:       # frame 0 -> 1 as a pair
        return data.frames[0], data.frames[1]
    return data.ref, data.mov


def measure(case, specs, repeats):
    """{label: dict(e, cpu, elements, message)} of R_P_sigma with each ``refine=`` spec of ``specs`` (label ->
    spec) on the case's pair; CPU seconds the minimum over ``repeats`` interleaved runs."""
    import femreg

    data = make_data(case)
    ref, mov = _pair(case, data)
    sl = roi_slices(ref.shape, data.spacing)
    t = truth(data, case, sl, frame=1)   # a sequence registers frame 0 -> 1 here
    lam = PROBES[case.probe].wavelength_mm
    out = {k: dict(cpu=np.inf) for k in specs}
    for _ in range(repeats):
        for label, spec in specs.items():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                c0 = time.process_time()
                res = femreg.register(ref, mov, spacing=data.spacing, origin=data.origin, refine=spec)
                dt = time.process_time() - c0
            o = out[label]
            o["cpu"] = min(o["cpu"], dt)
            if "e" not in o:
                o.update(e=errors(res.on_grid(), t, sl, lam)["e"], elements=int(res.mesh.t.shape[1]),
                         success=bool(res.success), passes=getattr(getattr(res, "refinement", None), "passes", []))
    return out


def selected_cases(all_cases, words: str, seed: int = 0) -> list:
    """The cases whose name contains one of the comma-separated ``words`` (all when empty), their seeds moved by
    ``seed``; BLAS set to one thread (before numpy's first use) so that CPU times compare run to run."""
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    ws = [w for w in words.split(",") if w]
    cases = [c for c in all_cases if not ws or any(w in c.name for w in ws)]
    return [dataclasses.replace(c, seed=c.seed + seed) for c in cases] if seed else cases


def warm_up():
    import femreg
    from forward import fields as F
    from forward.pairs import make_pair

    d = make_pair(F.compression(0.01), "L7", (12.0, 10.0), 30.0, 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin, refine=None)
        femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin, refine="auto")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="")
    ap.add_argument("--refine", default="auto",
                    help="auto (= deep), slip, norelax (the two-pass refinement without the local relaxation), "
                         "nofine (the default without its finer marking), nofill (without Refinement.fine_fill), nofinealpha (the default without "
                         "Refinement.fine_alpha), fine:G (its gate at G x the cut), "
                         "twopass (Refinement(): the default before deep), finealpha:F[:N] (the default with "
                         "Refinement.fine_alpha=F[, fine_alpha_ncc=N]), deep (deep_refinement), lowcut "
                         "(marking at a z-score of 2), lowcut:F (its feature test at F x the cut) or a number of passes")
    ap.add_argument("--against", default=None,
                    help="also this refine= (as --refine): the error change of --refine against it")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="out/refine_cost")
    ap.add_argument("--seed", type=int, default=0, help="added to every case's seed (other speckle and noise)")
    a = ap.parse_args(argv)
    cases = selected_cases(CASES, a.cases, a.seed)
    warm_up()
    specs = {"off": None, "refine": _spec(a.refine)}
    if a.against is not None:
        specs["against"] = _spec(a.against)
    vs = f" | e % {a.against} | points vs {a.against}" if a.against is not None else ""
    lines = [f"| case | e % off -> refine | points | CPU s off | CPU s refine | ratio | elements{vs} |\n",
             "|---|---|---|---|---|---|---|" + ("---|---|" if vs else "") + "\n"]
    worst, ratios, worst_vs = -np.inf, [], -np.inf
    for case in cases:
        r = measure(case, specs, a.repeats)
        o, f = r["off"], r["refine"]
        d = 100 * (f["e"] - o["e"])
        ratio = f["cpu"] / o["cpu"]
        worst, ratios = max(worst, d), ratios + [ratio]
        flag = "" if o["success"] == f["success"] else f" (success {o['success']} -> {f['success']})"
        extra = ""
        if a.against is not None:
            g = r["against"]
            dv = 100 * (f["e"] - g["e"])
            worst_vs = max(worst_vs, dv)
            extra = f" {100 * g['e']:.2f} | {dv:+.2f} |"
        lines.append(f"| {case.name} | {100 * o['e']:.2f} -> {100 * f['e']:.2f}{flag} | {d:+.2f} | {o['cpu']:.2f} | "
                     f"{f['cpu']:.2f} | {ratio:.2f} | {o['elements']} -> {f['elements']} |{extra}\n")
        print(lines[-1], end="", flush=True)
    summary = (f"\nlargest error increase {worst:+.2f} points; CPU time ratio median {np.median(ratios):.2f}, "
               f"max {np.max(ratios):.2f} ({len(ratios)} pairs)"
               + (f"; largest error increase against {a.against} {worst_vs:+.2f} points" if a.against else "") + "\n")
    md = "".join(lines) + summary
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.md").write_text(md)
    print(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
