r"""The paper's closing hypothesis, measured on the study's own cases: do SPREME-regularised displacements give
better shear-modulus images?

The method paper (arXiv 2508.19086) ends on a hypothesis: a displacement regularised with the momentum equation
(R_P_sigma, eq:dmreg2 in plane stress), inverted with the same plane-stress model (eq:cEq with
:math:`\bar\lambda = 2`), should give a better modulus image than one regularised by the strain magnitude (R_eps).
This module tests it without any registration of its own: it inverts the displacement every study case already
saved (``OUTDIR/cases/<key>.npz``: ``mesh_points``, ``mesh_cells``, ``u``) with :func:`femreg.invert` on the case's
own 2 mm mesh, for

* the 3D sequences with an inclusion, :data:`DATASETS` (HI, SI, mHI: Young's contrast 4, 0.5, 2 at equal Poisson
  ratio, hence the same shear-modulus contrast);
* the single-frame registration 1 -> 7 and the accumulated track 1 -> 20 (the study's ``pair`` and
  ``n_track_frames``; a study with other frames is reported with its own frames, and says so);
* every regulariser of the study, and the *true* displacement of the same frame on the same mesh ("true u": the
  best any registration could give with a 2D model of 3D data);
* both 2D models (plane stress, plane strain), once with femreg's beta rule (L-curve) and once with one fixed
  beta for all (:data:`FIXED_BETA`), so that only the displacement differs.

Scores (:func:`femreg.inversion.modulus_contrast`, elements fully inside / outside the 15 mm inclusion disk):
contrast error = :math:`|C/C_{true} - 1|` in %; "error vs true u" = :math:`|C/C_{true\,u} - 1|`, what the
registration adds to the error of the 2D model itself; modulus CNR = :math:`2(m_A - m_B)^2/(s_A^2 + s_B^2)` (the
paper's CNR_e formula applied to mu); CV bg = :math:`s_A/m_A`, the spread of mu over the background.

The inversions run as :func:`femreg.batch.run_tasks` tasks (Dask; one inversion per task).  Each result is
cached in ``OUTDIR/inversions/``: the modulus image (``<key>.npz``, :meth:`femreg.InversionResult.save`) and its
record (``<key>.json``, written last), both atomically; a key hashes the study case's key (which hashes every
setting of the registration), the model, beta and :data:`INVERT_SETTINGS`, so a rerun recomputes nothing and a
changed setting never reuses a stale result.  The true displacements are written there too
(``truth_<hash>.npz``), once per data set, frame and mesh.

Public names: :func:`hypothesis_section` (the report section, Markdown lines), :func:`run_inversions`,
:func:`format_table`, :func:`conclusion`, :func:`sequence_truth`, :class:`DatasetTruth`, :class:`Disk`,
:func:`load_study`, :data:`DATASETS`, :data:`MODELS`, :data:`FIXED_BETA`.
"""
from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from femreg.io import atomic_savez, atomic_write_text

__all__ = ["hypothesis_section", "run_inversions", "format_table", "conclusion", "sequence_truth", "DatasetTruth",
           "Disk", "load_study", "invert_task", "DATASETS", "MODELS", "FIXED_BETA", "BETAS", "CACHE_DIR"]

#: Data sets of the hypothesis (3D phantom with a stiff, a soft and a mildly stiff inclusion).
DATASETS = ("3d-HI", "3d-SI", "3d-mHI")
#: Frames the hypothesis asks for: single frame 1 -> 7 (indices 0 -> 6), accumulated to frame 20.
WANTED_PAIR = (0, 6)
WANTED_TRACK = 20
MODELS = ("plane-stress", "plane-strain")
#: One beta for every displacement (the beta rule's most common choice on registered data), so that only the
#: displacement differs between the rows of the second comparison.
FIXED_BETA = 0.03
#: (tag, beta): femreg's L-curve rule, and the fixed beta.
BETAS = (("rule", None), ("fixed", FIXED_BETA))
#: femreg.invert settings of every inversion here (part of the cache key).
INVERT_SETTINGS = {"regularization": "tv", "element_size": None, "region": None}
#: Sub-folder of the study's output with the cached inversions.
CACHE_DIR = "inversions"
_VERSION = 1
_LABELS = {"strain": "R_eps", "strain-incompressible": "R_eps_i", "momentum-strain": "R_P_eps",
           "momentum-stress": "R_P_sigma", "truth": "true u"}


# ----------------------------------------------------------------------------------------------------------------
# Ground truth of a data set
# ----------------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Disk:
    """The inclusion ROI in the imaging plane: (x - xc)^2 + (y - yc)^2 < r^2, mm; a callable (n, 2) -> (n,) bool
    (a class, not a closure, so that it travels to Dask workers)."""

    xc: float
    yc: float
    r: float

    def __call__(self, points):
        p = np.asarray(points, float)
        return (p[:, 0] - self.xc) ** 2 + (p[:, 1] - self.yc) ** 2 < self.r ** 2


@dataclass
class DatasetTruth:
    """What the scoring needs to know about a data set: the true shear-modulus contrast (inclusion / background),
    the inclusion ROI, and the true displacement ``displacement(k, points (n, 2) mm) -> (n, 2) mm`` of frame 0 -> k
    in frame-0 coordinates (as ``forward`` sequences give it)."""

    contrast: float
    roi: Disk
    displacement: Callable


def sequence_truth(spec: dict) -> DatasetTruth:
    """:class:`DatasetTruth` of a study case's data set, from its simulated sequence (``forward``, cached)."""
    from .study import load_case_sequence

    seq = load_case_sequence(spec)
    p = seq.params
    return DatasetTruth(contrast=float(p["inclusion_modulus"]) / float(p["background_modulus"]),
                        roi=Disk(float(p.get("inclusion_depth_mm", 30.0)), 0.0,
                                 float(p.get("inclusion_diameter_mm", 15.0)) / 2.0),
                        displacement=seq.true_displacement)


# ----------------------------------------------------------------------------------------------------------------
# One inversion (a Dask task)
# ----------------------------------------------------------------------------------------------------------------

def _read_json(path: Path):
    try:
        return json.loads(path.read_text()) if path.exists() else None
    except ValueError:      # torn by a crash before the atomic writer existed: recompute
        return None


def invert_task(job: dict, cachedir) -> dict:
    """Invert one displacement and score it; writes ``<key>.npz`` (the modulus image) then ``<key>.json`` (the
    record), atomically, into ``cachedir``.  A record already there (a task rescheduled after its worker died) is
    returned without recomputing.  ``job``: key, source (npz with mesh_points, mesh_cells, u), model, beta, roi
    (:class:`Disk`), contrast_true."""
    import warnings

    import femreg
    from femreg.inversion import modulus_contrast
    from femreg import RegistrationResult
    from skfem import MeshQuad1

    warnings.filterwarnings("ignore", category=RuntimeWarning)
    cachedir = Path(cachedir)
    rec_path = cachedir / f"{job['key']}.json"
    rec = _read_json(rec_path)
    if rec is not None and "error" not in rec:
        return rec
    with np.load(job["source"]) as z:
        mesh = MeshQuad1(z["mesh_points"], z["mesh_cells"])
        u = np.asarray(z["u"], float)
    # femreg.invert takes a RegistrationResult (or a callable); it reads only the mesh and the nodal field, so the
    # image geometry is nominal here.
    rr = RegistrationResult(mesh, u, shape=(2, 2), spacing=(1.0, 1.0), origin=tuple(mesh.p.min(axis=1)))
    t0 = time.perf_counter()
    inv = femreg.invert(rr, model=job["model"], beta=job["beta"], regularization=INVERT_SETTINGS["regularization"])
    seconds = time.perf_counter() - t0
    inv.save(cachedir / f"{job['key']}.npz")
    m = modulus_contrast(inv, job["roi"])
    truth = float(job["contrast_true"])
    rec = {"key": job["key"], "group": job["group"], "regularizer": job["regularizer"], "model": job["model"],
           "tag": job["tag"], "source": str(job["source"]), "contrast_true": truth, "contrast": m["contrast"],
           "contrast_error": 100.0 * abs(m["contrast"] / truth - 1.0), "CNR": m["CNR"],
           "cv_background": m["cv_background"], "edge_error_mm": m["edge_error_mm"], "beta": inv.beta,
           "beta_rule": inv.beta_rule, "success": inv.success, "message": inv.message,
           "n_el": int(inv.mesh.t.shape[1]), "invert_s": seconds}
    atomic_write_text(rec_path, json.dumps(rec, indent=1, default=float))
    return rec


# ----------------------------------------------------------------------------------------------------------------
# The study's cases -> inversion jobs
# ----------------------------------------------------------------------------------------------------------------

def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _groups(res):
    """[(dataset, kind, label, k, {regulariser: case spec}, notes)] for the hypothesis' data sets found in the
    study's settings, and a list of the rows the hypothesis wants that the study lacks."""
    from .study import make_case

    s = res.settings
    groups, missing = [], []
    a, b = (int(v) for v in s.pair)
    n = int(s.n_track_frames)
    for d in DATASETS:
        for kind, present, label, k, frames in (
                ("pair", d in s.single_datasets, f"frames {a + 1}->{b + 1}", b - a, tuple(s.pair)),
                ("track", d in s.track_datasets, f"accumulated 1->{n}", n - 1, n)):
            want = f"frames {WANTED_PAIR[0] + 1}->{WANTED_PAIR[1] + 1}" if kind == "pair" else \
                f"accumulated 1->{WANTED_TRACK}"
            if not present:
                missing.append(f"{d} {want} (not among the study's "
                               f"{'single-frame' if kind == 'pair' else 'tracked'} data sets)")
                continue
            if label != want:
                missing.append(f"{d} {want} (the study has {label}; shown instead)")
            specs = {r: make_case(s, kind, d, r, res.alphas[r], frames) for r in s.regularizers}
            groups.append((d, kind, label, k, specs))
    return groups, missing


def _case_ok(res, spec) -> bool:
    rec = res.records.get(spec["key"])
    return bool(rec) and "error" not in rec and (Path(res.outdir) / "cases" / f"{spec['key']}.npz").exists()


def _jobs(res, models, betas, truth_fn):
    """Every inversion the section needs: [(job, cached record or None)], the notes on missing cases."""
    cachedir = Path(res.outdir) / CACHE_DIR
    groups, missing = _groups(res)
    out = []
    truths = {}

    def truth_of(spec):
        tk = json.dumps({k: spec[k] for k in ("dataset", "seed", "snr_db", "n_frames", "sequence_options")},
                        sort_keys=True, default=str)
        if tk not in truths:
            truths[tk] = truth_fn(spec)
        return truths[tk]

    for d, kind, label, k, specs in groups:
        ok = {r: sp for r, sp in specs.items() if _case_ok(res, sp)}
        for r in specs:
            if r not in ok:
                missing.append(f"{d} {label} {_LABELS.get(r, r)} (case `{specs[r]['key']}` failed or not run)")
        if not ok:
            continue
        group = f"{d}|{kind}|{label}"
        # true displacement on the mesh of one of the group's cases (they share the mesh: same settings)
        mesh_spec = ok.get("momentum-stress") or next(iter(ok.values()))
        mesh_npz = Path(res.outdir) / "cases" / f"{mesh_spec['key']}.npz"
        with np.load(mesh_npz) as z:
            p, t = np.asarray(z["mesh_points"], float), np.asarray(z["mesh_cells"], np.int64)
        tkey = _hash({"dataset": {kk: mesh_spec[kk] for kk in ("dataset", "seed", "snr_db", "n_frames",
                                                               "sequence_options")}, "k": int(k),
                      "mesh": hashlib.sha256(p.tobytes() + t.tobytes()).hexdigest()})
        truth_npz = cachedir / f"truth_{d}_{k}_{tkey}.npz"
        sources = {r: (Path(res.outdir) / "cases" / f"{sp['key']}.npz", sp["key"]) for r, sp in ok.items()}
        sources["truth"] = (truth_npz, f"truth_{tkey}")
        for r, (src, src_key) in sources.items():
            for model in models:
                for tag, beta in betas:
                    key = (f"{d}_{kind}{k}_{r}_{model}_{tag}_"
                           + _hash({"source": src_key, "model": model, "beta": beta, "invert": INVERT_SETTINGS,
                                    "version": _VERSION}))
                    job = {"key": key, "group": group, "regularizer": r, "model": model, "tag": tag, "beta": beta,
                           "source": str(src)}
                    rec = _read_json(cachedir / f"{key}.json")
                    if rec is None or "error" in rec:
                        tr = truth_of(mesh_spec)
                        job.update(roi=tr.roi, contrast_true=tr.contrast)
                        if r == "truth" and not truth_npz.exists():
                            v = np.asarray(tr.displacement(k, p.T), float)
                            u = np.empty(2 * p.shape[1])
                            u[0::2], u[1::2] = v[:, 0], v[:, 1]
                            cachedir.mkdir(parents=True, exist_ok=True)
                            atomic_savez(truth_npz, mesh_points=p, mesh_cells=t, u=u, frame=np.int64(k))
                        rec = None
                    out.append((job, rec))
    return out, missing


def run_inversions(res, *, models=MODELS, betas=BETAS, jobs: int | None = None, client=None,
                   scheduler: str | None = None, progress: bool | None = None,
                   truth: Callable = sequence_truth, stats: dict | None = None):
    """Invert every displacement the hypothesis needs (module docstring), reusing cached results.

    ``res``: a :class:`paperstudy.study.StudyResult` (settings, alphas, records, outdir; ``runs`` gives the default
    ``jobs`` / ``scheduler``).  Parallel on :func:`femreg.batch.run_tasks`: ``client`` (a Dask client), else
    ``scheduler``, else ``jobs`` local processes (1 = serially in this process).  ``truth``: spec ->
    :class:`DatasetTruth` (default :func:`sequence_truth`), called only for data sets with something to compute.
    Returns (records, missing): the inversion records in job order and the notes on rows the study lacks;
    ``stats["computed"]`` counts the inversions run."""
    from femreg.batch import Task, run_tasks

    last = (getattr(res, "runs", None) or [{}])[-1]
    jobs = int(last.get("jobs", 1) if jobs is None else jobs)
    scheduler = last.get("scheduler") if scheduler is None and client is None else scheduler
    if progress is None:
        progress = sys.stderr.isatty()
    cachedir = Path(res.outdir) / CACHE_DIR
    pairs, missing = _jobs(res, models, betas, truth)
    todo = [job for job, rec in pairs if rec is None]
    if stats is not None:
        stats["computed"] = stats.get("computed", 0) + len(todo)
    done = {}
    if todo:
        cachedir.mkdir(parents=True, exist_ok=True)
        # the beta rule sweeps up to seven betas: those tasks are the long ones, run them first
        tasks = [Task(j["key"], invert_task, (j, str(cachedir)), priority=2 if j["beta"] is None else 1)
                 for j in todo]
        workers = 0 if client is None and scheduler is None and jobs <= 1 else jobs
        for key, out in run_tasks(tasks, client=client, workers=workers, scheduler=scheduler, progress=progress,
                                  desc="modulus inversions").items():
            done[key] = out.value if out.ok else {"key": key, "error": out.error}
    records = [rec if rec is not None else done[job["key"]] for job, rec in pairs]
    for job, rec in zip((j for j, _ in pairs), records):
        rec.setdefault("group", job["group"])
        rec.setdefault("regularizer", job["regularizer"])
        rec.setdefault("model", job["model"])
        rec.setdefault("tag", job["tag"])
    return records, missing


# ----------------------------------------------------------------------------------------------------------------
# Table and conclusion
# ----------------------------------------------------------------------------------------------------------------

def _rows(records):
    """Records -> rows {group, dataset, label, model, regularizer, truth, <tag>: record}, in table order (data
    set and displacement as the study lists them, then model, then regulariser with the true u last)."""
    rows = {}
    for rec in records:
        d, _, label = rec["group"].split("|")
        row = rows.setdefault((rec["group"], rec["model"], rec["regularizer"]),
                              {"group": rec["group"], "dataset": d, "label": label, "model": rec["model"],
                               "regularizer": rec["regularizer"]})
        row[rec["tag"]] = rec
        if "contrast_true" in rec:
            row["truth"] = rec["contrast_true"]
    groups = list(dict.fromkeys(rec["group"] for rec in records))
    models, regs = list(MODELS), list(_LABELS)
    return sorted(rows.values(), key=lambda r: (
        groups.index(r["group"]), models.index(r["model"]) if r["model"] in models else len(models),
        regs.index(r["regularizer"]) if r["regularizer"] in regs else len(regs)))


def _num(q, name, fmt):
    v = None if q is None or "error" in q else q.get(name)
    return "--" if v is None or not np.isfinite(v) else format(v, fmt)


def format_table(records, betas=BETAS) -> list:
    """Markdown table lines: one row per (data set, displacement, model, regulariser); per beta setting the
    contrast, its error against the true contrast and against the inversion of the true u (same data set,
    displacement, model and beta), CNR and CV bg."""
    rows = _rows(records)
    ref = {(r["dataset"], r["label"], r["model"]): r for r in rows if r["regularizer"] == "truth"}
    head = "| data set | displacement | model | regulariser | contrast (true) |"
    for tag, beta in betas:
        name = "rule" if beta is None else f"beta {beta:g}"
        head += (f" {name}: beta |" if beta is None else "") + (f" {name}: contrast | error % | error vs true u % |"
                                                                " CNR | CV bg % |")
    L = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        c = ref.get((r["dataset"], r["label"], r["model"]))
        cells = []
        for tag, beta in betas:
            q = r.get(tag)
            qt = c.get(tag) if c else None
            vs = None
            if q and qt and "error" not in q and "error" not in qt:
                vs = 100.0 * abs(q["contrast"] / qt["contrast"] - 1.0)
            if beta is None:
                cells.append(_num(q, "beta", ".2g"))
            cells += [_num(q, "contrast", ".2f") + ("" if not q or "error" in q or q.get("success", True) else "*"),
                      _num(q, "contrast_error", ".1f"), "--" if vs is None else f"{vs:.1f}", _num(q, "CNR", ".2f"),
                      "--" if not q or "error" in q else f"{100 * q['cv_background']:.1f}"]
        truth = f"{r['truth']:g}" if "truth" in r else "--"
        L.append(f"| {r['dataset']} | {r['label']} | {r['model']} | {_LABELS.get(r['regularizer'], r['regularizer'])}"
                 f" | {truth} | " + " | ".join(cells) + " |")
    return L


def _scores(records, model, tag):
    """{label: {regulariser: [(dataset, contrast error %, error vs true u %, CNR)]}} of one model / beta."""
    out = {}
    by = {(r["group"], r["regularizer"]): r for r in records
          if r.get("model") == model and r.get("tag") == tag and "error" not in r}
    for (group, reg), rec in by.items():
        d, _, label = group.split("|")
        t = by.get((group, "truth"))
        vs = 100.0 * abs(rec["contrast"] / t["contrast"] - 1.0) if t else float("nan")
        out.setdefault(label, {}).setdefault(reg, []).append((d, rec["contrast_error"], vs, rec["CNR"]))
    return out


def conclusion(records, *, model="plane-stress", betas=BETAS, a="momentum-stress", b="strain") -> list:
    """The verdict, computed from the numbers: per displacement (single frame, accumulated) and beta setting,
    whether ``a`` (R_P_sigma) + ``model`` inversion beats ``b`` (R_eps), and by how much, in both scorings (mean
    contrast error against the true contrast, and against the inversion of the true u), over the data sets both
    have; with the modulus CNR and per-data-set win counts.  Returns Markdown bullet lines."""
    L = []
    tally = ([], [])          # per scoring: did a beat b, for each (displacement, beta) compared
    la, lb = _LABELS[a], _LABELS[b]
    for tag, beta in betas:
        bname = "beta rule" if beta is None else f"beta {beta:g}"
        for label, regs in _scores(records, model, tag).items():
            if a not in regs or b not in regs:
                L.append(f"- {label}, {model} inversion, {bname}: no verdict ({la} or {lb} missing).")
                continue
            A = {d: v for d, *v in regs[a]}
            B = {d: v for d, *v in regs[b]}
            ds = sorted(set(A) & set(B))
            parts = []
            for i, (what, unit) in enumerate((("against the true contrast", "mean contrast error"),
                                              ("against the true-u inversion", "mean error vs true u"))):
                ma, mb = np.mean([A[d][i] for d in ds]), np.mean([B[d][i] for d in ds])
                if not (np.isfinite(ma) and np.isfinite(mb)):
                    parts.append(f"{what}: not scored")
                    continue
                wins = sum(A[d][i] < B[d][i] for d in ds)
                tally[i].append(ma < mb)
                how = (f"**beats** {lb} by {mb - ma:.1f} points" if ma < mb else
                       f"does **not** beat {lb} ({ma - mb:.1f} points worse)")
                parts.append(f"{what} {la} {how}: {unit} {ma:.1f} % vs {mb:.1f} %, better in {wins} of {len(ds)} "
                             "data set(s)")
            if "truth" in regs:
                T = {d: v for d, *v in regs["truth"]}
                parts.append(f"the true displacement itself: {np.mean([T[d][0] for d in ds if d in T]):.1f} % "
                             "contrast error (the 2D model's own)")
            ca, cb = np.mean([A[d][2] for d in ds]), np.mean([B[d][2] for d in ds])
            L.append(f"- {label}, {model} inversion, {bname} ({', '.join(ds)}): " + "; ".join(parts)
                     + f"; modulus CNR {ca:.2f} vs {cb:.2f}.")
    if tally[0]:
        L.insert(0, f"- **In short**: {la} + {model} inversion beats {lb} against the true contrast in "
                    f"{sum(tally[0])} of {len(tally[0])} comparisons, and against the inversion of the true "
                    f"displacement in {sum(tally[1])} of {len(tally[1])} (displacements x beta settings below).")
    return L


def _means(records, models, betas):
    """Mean lines per displacement, model and beta: contrast error / error vs true u / CNR per regulariser."""
    L = []
    for model in models:
        for tag, beta in betas:
            bname = "beta rule" if beta is None else f"beta {beta:g}"
            for label, regs in _scores(records, model, tag).items():
                ds = sorted({d for v in regs.values() for d, *_ in v})
                L.append(f"- {label}, {model} inversion, {bname} ({', '.join(ds)}): mean contrast error / error vs "
                         "true-u inversion / CNR: " + "; ".join(
                             f"{_LABELS.get(g, g)} {np.mean([v[1] for v in regs[g]]):.1f} % / "
                             f"{np.nanmean([v[2] for v in regs[g]]):.1f} % / {np.mean([v[3] for v in regs[g]]):.2f}"
                             for g in sorted(regs, key=lambda g: list(_LABELS).index(g) if g in _LABELS else 99))
                         + ".")
    return L


def hypothesis_section(res, *, models=MODELS, betas=BETAS, jobs: int | None = None, client=None,
                       scheduler: str | None = None, progress: bool | None = None,
                       truth: Callable = sequence_truth, stats: dict | None = None) -> list:
    """The study report's section on the paper's closing hypothesis (Markdown lines): runs or reuses the
    inversions (:func:`run_inversions`, same arguments), then the table, the means, the computed conclusion, and
    which rows the study's case set lacks.  Also writes ``OUTDIR/inversions/summary.json``.  Never raises: a
    failure becomes a line of the section (the rest of the report must not be lost)."""
    head = ["## Shear-modulus inversion: the paper's closing hypothesis", ""]
    try:
        return head + _section(res, models, betas, jobs, client, scheduler, progress, truth,
                               {} if stats is None else stats)
    except Exception as exc:  # noqa: BLE001 - the report goes on without this section
        return head + [f"(not computed: {type(exc).__name__}: {exc})", ""]


def _section(res, models, betas, jobs, client, scheduler, progress, truth, stats) -> list:
    t0 = time.perf_counter()
    n0 = stats.get("computed", 0)
    records, missing = run_inversions(res, models=models, betas=betas, jobs=jobs, client=client,
                                      scheduler=scheduler, progress=progress, truth=truth, stats=stats)
    wall = time.perf_counter() - t0
    L = ["Does a SPREME-regularised displacement, inverted with the matching 2D model, give a better modulus "
          "image?  Each regulariser's displacement from the cases above is inverted with `femreg.invert` on its "
          f"own mesh ({' and '.join(models)} model{'s' if len(models) > 1 else ''}), "
          + " and ".join(("with femreg's beta rule (L-curve)" if b is None else f"at one beta {b:g} for all")
                         for _, b in betas) + ".  Contrast = mean relative shear modulus of the "
          "elements fully inside the inclusion / fully outside (true: Young's contrast at equal Poisson ratio); "
          "\"error vs true u\" compares with the inversion of the *true* displacement on the same mesh (what the "
          "registration adds to the error of the 2D model of 3D data); CNR: the CNR_e formula applied to mu; "
          "CV bg: spread of mu over the background.  A contrast marked * comes from an inversion not flagged "
          "successful.  Cached in `inversions/` (reused on a rerun).", ""]
    errs = [r for r in records if "error" in r]
    n_new = stats.get("computed", 0) - n0
    if records:
        L += format_table(records, betas) + [""]
        L += ["**Means over the data sets:**", ""] + _means(records, models, betas) + [""]
        L += ["**Conclusion** (R_P_sigma + plane-stress inversion against R_eps + plane-stress inversion, computed "
              "from the table):", ""]
        L += conclusion(records, betas=betas) + [""]
    else:
        L += ["No case of the hypothesis' data sets in this study: nothing to invert.", ""]
    if missing:
        L += ["Rows the hypothesis asks for that this study lacks: " + "; ".join(missing) + ".", ""]
    if errs:
        L += [f"{len(errs)} inversion(s) failed: " + "; ".join(f"`{r['key']}`: {r['error']}" for r in errs[:5]), ""]
    secs = [r.get("invert_s", 0.0) for r in records if "error" not in r]
    if records:
        L += [f"{len(records)} inversions ({n_new} computed now, {wall:.0f} s wall; "
              f"{sum(secs):.0f} s of inversion time in total, median {np.median(secs) if secs else 0:.1f} s).", ""]
    try:
        atomic_write_text(Path(res.outdir) / CACHE_DIR / "summary.json",
                          json.dumps({"records": records, "missing": missing}, indent=1, default=float))
    except OSError:
        pass
    return L


# ----------------------------------------------------------------------------------------------------------------
# A finished study's folder
# ----------------------------------------------------------------------------------------------------------------

def load_study(outdir):
    """A :class:`paperstudy.study.StudyResult` of a study folder (``settings.json``, ``alphas.json``,
    ``cases/*.json``), enough for :func:`hypothesis_section`; FileNotFoundError if it holds no study."""
    import dataclasses

    from .study import StudyResult, StudySettings

    outdir = Path(outdir)
    sj, aj = outdir / "settings.json", outdir / "alphas.json"
    if not (sj.exists() and aj.exists()):
        raise FileNotFoundError(f"{outdir} holds no study (settings.json and alphas.json)")
    raw = json.loads(sj.read_text())
    kw = {}
    for f in dataclasses.fields(StudySettings):
        if f.name not in raw:
            continue
        v = raw[f.name]
        if isinstance(v, list):
            v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
        kw[f.name] = v
    s = StudySettings(**kw)
    alphas = {k: float(v) for k, v in json.loads(aj.read_text())["alphas"].items()}
    records = {}
    for p in sorted((outdir / "cases").glob("*.json")):
        rec = _read_json(p)
        if rec is not None:
            records[rec["key"]] = rec
    runs = _read_json(outdir / "runs.json") or []
    return StudyResult(settings=s, alphas=alphas, sweep={}, records=records, outdir=outdir,
                       report=outdir / "report.md", wall_s=0.0, runs=runs)
