"""The paper's closing hypothesis, measured: do SPREME-regularised displacements give better shear-modulus images?

For the simulated 3D sequences (forward.get_sequence("3d", HI / SI / mHI, seed=0)), each regulariser's
displacement -- ``femreg.register`` frames 1 -> 7 (indices 0 -> 6) and ``femreg.track`` accumulated to frame 20
(index 19, current-grid accumulation, block-matching start of every increment, as the study) -- is inverted with
``femreg.invert`` on the registration's own mesh (2 mm elements) with the plane-stress model (consistent with
R_P_sigma) and the plane-strain model (consistent with R_P_eps), once with the default beta rule and once with one
fixed beta for all (:data:`FIXED_BETA`), and scored against the true shear-modulus contrast (Young's contrast
4 / 0.5 / 2 at equal Poisson ratio):

* contrast error = |C / C_true - 1| in %, C = mean mu in the inclusion / mean mu in the background (elements
  fully inside / outside the 15 mm disk; :func:`femreg.inversion.modulus_contrast`);
* modulus CNR = 2 (m_A - m_B)^2 / (s_A^2 + s_B^2) (the paper's CNR_e formula applied to mu);
* CV bg = s_A / m_A, the spread of mu over the background (0 for a perfect image of this phantom).

A row "true u" inverts the true displacement on the same mesh: the best any registration could give with a 2D
model of 3D data; "error vs true u" = |C / C_true-u - 1| is what the registration adds to that model error.

Usage: ``python benchmarks/inversion_hypothesis.py [--out DIR] [--jobs 2] [--quick]``; writes ``DIR/table.md``,
``DIR/rows.json`` and one ``.npz`` per displacement (resumes: finished cases are reused).  ``--quick``: 3D HI only,
frames 1 -> 7 only.  The study can call :func:`hypothesis_table`.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

REGULARIZERS = ("strain", "strain-incompressible", "momentum-strain", "momentum-stress")
LABELS = {"strain": "R_eps", "strain-incompressible": "R_eps_i", "momentum-strain": "R_P_eps",
          "momentum-stress": "R_P_sigma", "truth": "true u"}
DATASETS = ("HI", "SI", "mHI")
KINDS = (("pair", "frames 1->7"), ("track", "accumulated 1->20"))
SETTINGS = dict(element_size=2.0, margin=1.0)
MODELS = ("plane-stress", "plane-strain")
#: The second comparison uses one beta for every displacement (the rule's most common choice on registered data),
#: so that only the displacement differs.
FIXED_BETA = 0.03


def _sequence(inc):
    import forward

    return forward.get_sequence("3d", inc, seed=0)


def _roi(seq):
    xc = float(seq.params.get("inclusion_depth_mm", 30.0))
    r = float(seq.params.get("inclusion_diameter_mm", 15.0)) / 2.0
    return lambda p: (np.asarray(p)[:, 0] - xc) ** 2 + np.asarray(p)[:, 1] ** 2 < r * r


def _displacement(inc, reg, kind, outdir: Path):
    """The registration (cached as npz) -> path."""
    import femreg

    path = outdir / f"u_{inc}_{reg}_{kind}.npz"
    if path.exists():
        return path
    seq = _sequence(inc)
    kw = dict(spacing=seq.spacing, origin=seq.origin, **SETTINGS)
    t0 = time.perf_counter()
    if kind == "pair":
        res = femreg.register(seq.frames[0], seq.frames[6], regularizer=reg, **kw)
    else:
        res = femreg.track(seq.frames[:20], regularizer=reg, mode="accumulate", grid="current", init="blockmatch",
                           **kw)[-1]
    res.save(path.with_suffix(".tmp.npz"), seconds=np.float64(time.perf_counter() - t0))
    os.replace(path.with_suffix(".tmp.npz"), path)
    return path


def _case(args):
    inc, reg, kind, model, outdir = args
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[v] = "1"
    import femreg
    from femreg.inversion import modulus_contrast

    outdir = Path(outdir)
    rec_path = outdir / f"row_{inc}_{reg}_{kind}_{model}.json"
    if rec_path.exists():
        return json.loads(rec_path.read_text())
    seq = _sequence(inc)
    truth = seq.params["inclusion_modulus"] / seq.params["background_modulus"]
    k = 6 if kind == "pair" else 19
    if reg == "truth":
        rr = femreg.load_result(_displacement(inc, "momentum-stress", kind, outdir))   # its mesh
        mesh = rr.mesh
        v = seq.true_displacement(k, mesh.p.T)
        u = np.empty(2 * mesh.p.shape[1])
        u[0::2], u[1::2] = v[:, 0], v[:, 1]
        rr = femreg.RegistrationResult(mesh, u, shape=rr.shape, spacing=rr.spacing, origin=rr.origin)
    else:
        rr = femreg.load_result(_displacement(inc, reg, kind, outdir))
    row = {"dataset": f"3d-{inc}", "regularizer": reg, "kind": kind, "model": model, "truth": truth}
    for tag, beta in (("rule", None), ("fixed", FIXED_BETA)):
        t0 = time.perf_counter()
        inv = femreg.invert(rr, model=model, beta=beta)
        seconds = time.perf_counter() - t0
        inv.save(outdir / f"mu_{inc}_{reg}_{kind}_{model}_{tag}.npz")
        m = modulus_contrast(inv, _roi(seq))
        row[tag] = {"contrast": m["contrast"], "contrast_error": 100 * abs(m["contrast"] / truth - 1),
                    "CNR": m["CNR"], "cv_background": m["cv_background"], "beta": inv.beta,
                    "edge_error_mm": m["edge_error_mm"],
                    "success": inv.success, "invert_s": seconds}
    row["n_el"] = int(inv.mesh.t.shape[1])
    rec_path.write_text(json.dumps(row, indent=1, default=float))
    return row


def hypothesis_table(outdir, *, datasets=DATASETS, kinds=("pair", "track"), models=MODELS, jobs: int = 2,
                     log=print, only_existing: bool = False) -> str:
    """Run (or reuse) every case and return the Markdown table with a verdict paragraph.  ``only_existing``:
    invert only the displacements already in ``outdir`` (a partial run), compute no new registration."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    for inc in datasets:       # generate/cached sequences in the parent, so workers only read
        _sequence(inc)
    regs = REGULARIZERS + ("truth",)
    # registrations first (the 'truth' rows need the R_P_sigma mesh), then inversions
    reg_cases = [(inc, r, k, str(outdir)) for inc in datasets for k in kinds for r in REGULARIZERS]
    if only_existing:
        have = {(i, k) for i in datasets for k in kinds
                if all((outdir / f"u_{i}_{r}_{k}.npz").exists() for r in REGULARIZERS)}
        reg_cases = [c for c in reg_cases if (c[0], c[2]) in have]
    inv_cases = [(inc, r, k, m, str(outdir)) for inc in datasets for k in kinds for m in models for r in regs
                 if any(c[0] == inc and c[2] == k for c in reg_cases)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=jobs) as ex:
        list(ex.map(_displacement_worker, reg_cases))
        log(f"registrations done ({time.perf_counter() - t0:.0f} s)")
        rows = list(ex.map(_case, inv_cases))
    (outdir / "rows.json").write_text(json.dumps(rows, indent=1, default=float))
    return format_table(rows)


def _displacement_worker(args):
    inc, reg, kind, outdir = args
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[v] = "1"
    import warnings
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    return str(_displacement(inc, reg, kind, Path(outdir)))


def format_table(rows, models=MODELS) -> str:
    """Markdown: one row per (data set, displacement, model, regulariser); the contrast error against the true
    modulus contrast and against the inversion of the true displacement ("vs true u": what the registration adds
    to the model error), for the beta rule and for one fixed beta."""
    ref = {(r["dataset"], r["kind"], r["model"]): r for r in rows if r["regularizer"] == "truth"}
    L = [f"| data set | displacement | model | regulariser | contrast (true) | rule: beta | contrast | error % | "
         f"error vs true u % | CNR | CV bg % | beta {FIXED_BETA:g}: contrast | error % | error vs true u % | CNR | "
         "CV bg % |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["model"] not in models:
            continue
        c = ref.get((r["dataset"], r["kind"], r["model"]))
        cells = []
        for tag in ("rule", "fixed"):
            q = r[tag]
            vs = 100 * abs(q["contrast"] / c[tag]["contrast"] - 1) if c else float("nan")
            cells += ([f"{q['beta']:.2g}"] if tag == "rule" else []) + [
                f"{q['contrast']:.2f}", f"{q['contrast_error']:.1f}", f"{vs:.1f}", f"{q['CNR']:.2f}",
                f"{100 * q.get('cv_background', float('nan')):.1f}"]
        L.append(f"| {r['dataset']} | {dict(KINDS)[r['kind']]} | {r['model']} | {LABELS[r['regularizer']]} | "
                 f"{r['truth']:g} | " + " | ".join(cells) + " |")
    L += [""]
    for kind, kname in KINDS:
        for model in models:
            sel = {(r["dataset"], r["regularizer"]): r for r in rows if r["kind"] == kind and r["model"] == model}
            ds = sorted({d for d, _ in sel})
            if not ds:
                continue
            for tag, tname in (("rule", "beta rule"), ("fixed", f"beta {FIXED_BETA:g}")):
                def vs(d, g):
                    return 100 * abs(sel[(d, g)][tag]["contrast"] / sel[(d, "truth")][tag]["contrast"] - 1)

                mean = {g: (np.mean([sel[(d, g)][tag]["contrast_error"] for d in ds]),
                            np.mean([vs(d, g) for d in ds]),
                            np.mean([sel[(d, g)][tag]["CNR"] for d in ds])) for g in REGULARIZERS + ("truth",)}
                win_e = sum(vs(d, "momentum-stress") < vs(d, "strain") for d in ds)
                win_c = sum(sel[(d, "momentum-stress")][tag]["CNR"] > sel[(d, "strain")][tag]["CNR"] for d in ds)
                L.append(f"- {kname}, {model} inversion, {tname} ({', '.join(ds)}): mean contrast error / error vs "
                         "true-u inversion / CNR: " + "; ".join(
                             f"{LABELS[g]} {mean[g][0]:.1f} % / {mean[g][1]:.1f} % / {mean[g][2]:.2f}" for g in mean)
                         + f".  R_P_sigma closer to the true-u inversion than R_eps in {win_e} of {len(ds)}, "
                           f"higher CNR in {win_c} of {len(ds)}.")
    return "\n".join(L)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(REPO / "out" / "inversion_hypothesis"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="3D HI, frames 1 -> 7 only")
    ap.add_argument("--only-existing", action="store_true",
                    help="invert only the displacements already computed in --out (no new registrations)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    kw = dict(datasets=("HI",), kinds=("pair",)) if args.quick else {}
    table = hypothesis_table(args.out, jobs=args.jobs, only_existing=args.only_existing, **kw)
    (Path(args.out) / "table.md").write_text(table + "\n")
    rows = json.loads((Path(args.out) / "rows.json").read_text())
    (Path(args.out) / "table_plane_stress.md").write_text(format_table(rows, models=("plane-stress",)) + "\n")
    print(table)
    print(f"\n{time.perf_counter() - t0:.0f} s; wrote {Path(args.out) / 'table.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
