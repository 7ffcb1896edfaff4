"""Robustness benchmark: femreg's regularisers and the peers users would otherwise pick, on one matrix of simulated
RF pairs (probes x fields x image sizes x SNR), same pairs, same error metric, one run.

Pairs come from :mod:`forward.pairs` (the same scatterers moved by the field: exact truth).  Methods:

* femreg with defaults, the four regularisers (R_eps, R_eps_i, R_P_eps, R_P_sigma):
  ``femreg.register(ref, mov, spacing=..., origin=..., regularizer=...)``;
* R_P_sigma with the paper's procedure (``strategy="paper"`` where ``register`` has it; otherwise the default
  procedure *is* the paper's and the R_P_sigma result is reported again);
* peers (:mod:`benchmarks.peers`): NCC block matching, SimpleITK B-spline, scikit-image TV-L1 optical flow.

The sequence case (10 frames, 1 % per frame) is measured frame 0 -> 9: ``femreg.track`` for femreg, consecutive
pairs accumulated for the peers (``U_k(x) = U_{k-1}(x) + u_k(x + U_{k-1}(x))``, least-squares strain of ``U``).

Error metric, over an ROI inset from the image borders by ``max(2 mm, 10 %)`` on every side, on the reference
pixel grid (every ``~0.1 mm`` axially): relative L2 errors as :func:`femreg.metrics.field_errors` --
``e`` total strain ``||e_m - e_t|| / ||e_t||`` with ``e:e = e_xx^2 + e_yy^2 + 2 e_xy^2``; ``exx``, ``eyy``; ``ux``,
``uy`` displacement -- and ``hop``: the fraction of ROI pixels where ``|u_x - u_x^t|`` exceeds a quarter of the
acoustic wavelength ``c / f0`` (half the RF period in depth; a peak hop is one RF period).  Pixels a method leaves
undefined (NaN) count as zero displacement / strain.  Wall and CPU time (``time.process_time``) per method.

Outputs (``--out``, default ``out/robustness/``): ``results.csv`` (one row per case x method), ``results.md``
(the Markdown tables printed at the end) and ``<case>.png`` per case: the axial strain of every method side by side,
truth first, one colour scale, the ROI outlined.

Run: ``python benchmarks/robustness.py`` (full matrix, 151 s on 2 cores) or ``--quick`` (6 cases);
``--cases comp,shear`` selects cases whose name contains any of the words; ``--methods`` likewise (a method's full
name selects that method alone); ``--refine none|auto|N`` sets femreg's ``refine=`` for the pairs.  The peers'
results are cached in ``<out>/peer_cache`` (keyed by the case and the source of the simulator and of the peers),
so a rerun after a change to femreg recomputes femreg only (``--no-cache`` recomputes everything); the times
printed for cached peers are those of the run that computed them.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import inspect
import json
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import peers  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import PROBES, make_pair, make_sequence  # noqa: E402


# --------------------------------------------------------------------------------------------------------------
# The matrix
# --------------------------------------------------------------------------------------------------------------

@dataclass
class Case:
    name: str
    field: object            # callable () -> field (built lazily: the FE inclusions solve once, cached)
    probe: str
    size_mm: tuple
    snr_db: float
    top_mm: float = 2.0
    seed: int = 0
    quick: bool = False
    sequence: bool = False
    notes: str = ""


def _inc(kind, model, level):
    return lambda: F.Inclusion(kind, model, level)


CASES = [
    Case("comp0.2_L7", lambda: F.compression(0.002), "L7", (30, 30), 30),
    Case("comp1_paper", lambda: F.compression(0.01), "paper", (40, 30), 20, quick=True),
    Case("comp3_L7", lambda: F.compression(0.03), "L7", (30, 30), 30, quick=True),
    Case("comp5_paper", lambda: F.compression(0.05), "paper", (40, 30), 25),
    Case("comp8_L3", lambda: F.compression(0.08), "L3", (50, 40), 30),
    Case("shear_L7", lambda: F.shear_rotation(0.01), "L7", (30, 30), 30, quick=True,
         notes="1 % compression + 0.6 % simple shear + 0.1 deg rotation"),
    Case("rot2_L12", lambda: F.shear_rotation(0.01, shear=0.0, rotation_deg=2.0), "L12", (30, 30), 25,
         notes="1 % compression + 2 deg in-plane rotation"),
    Case("bend_paper", lambda: F.Bending(0.002, 0.02, 40.0), "paper", (40, 40), 25, quick=True,
         notes="axial strain 0.2 -> 2 % across the width"),
    Case("stiff-pstrain1_paper", _inc("stiff", "plane-strain", 0.01), "paper", (35, 30), 20),
    Case("stiff-pstrain4_L7", _inc("stiff", "plane-strain", 0.04), "L7", (30, 30), 30, quick=True),
    Case("soft-pstrain4_paper", _inc("soft", "plane-strain", 0.04), "paper", (35, 30), 25),
    Case("soft-pstrain1_L15", _inc("soft", "plane-strain", 0.01), "L15", (15, 15), 40, top_mm=12.5),
    Case("stiff-pstress1_L3", _inc("stiff", "plane-stress", 0.01), "L3", (40, 40), 15, quick=True,
         notes="low-frequency probe, 0.5 mm line pitch"),
    Case("stiff-pstress4_paper", _inc("stiff", "plane-stress", 0.04), "paper", (35, 30), 20),
    Case("soft-pstress1_L12", _inc("soft", "plane-stress", 0.01), "L12", (25, 25), 30, top_mm=7.5),
    Case("soft-pstress4_L7", _inc("soft", "plane-stress", 0.04), "L7", (30, 30), 10, notes="SNR 10 dB"),
    Case("comp1_paper_80x50", lambda: F.compression(0.01), "paper", (80, 50), 20),
    Case("seq10x1_L7", lambda: F.compression(0.01), "L7", (20, 20), 30, sequence=True,
         notes="10 frames at 1 % per frame, frame 0 -> 9 (9 %)"),
]

FEMREG_METHODS = {"R_eps": "strain", "R_eps_i": "strain-incompressible", "R_P_eps": "momentum-strain",
                  "R_P_sigma": "momentum-stress"}
PAPER_METHOD = "R_P_sigma paper"
PEER_METHODS = {"NCC BM": peers.ncc_block_match, "B-spline (SimpleITK)": peers.bspline_sitk,
                "TV-L1 (skimage)": peers.optical_flow_skimage}
ALL_METHODS = list(FEMREG_METHODS) + [PAPER_METHOD] + list(PEER_METHODS)


def _has_strategy() -> bool:
    import femreg

    return "strategy" in inspect.signature(femreg.register).parameters


# --------------------------------------------------------------------------------------------------------------
# Methods
# --------------------------------------------------------------------------------------------------------------

_GRID_KEYS = ("ux", "uy", "exx", "eyy", "exy")


#: ``refine=`` given to femreg's pair registrations (``--refine``); ``_UNSET``: register's own default.
_UNSET = object()
REFINE = _UNSET


def _refine_kw() -> dict:
    return {} if REFINE is _UNSET else {"refine": REFINE}


def _femreg_pair(ref, mov, spacing, origin, regularizer, paper):
    import femreg

    kw = dict(spacing=spacing, origin=origin, regularizer=regularizer)
    if paper:
        kw["strategy"] = "paper"
    else:
        kw.update(_refine_kw())
    res = femreg.register(ref, mov, **kw)
    g = res.on_grid()
    msg = "" if res.success else f"success=False: {res.message}"
    return {k: g[k] for k in _GRID_KEYS}, msg


def _femreg_sequence(frames, spacing, origin, regularizer, paper):
    import femreg

    kw = dict(spacing=spacing, origin=origin, regularizer=regularizer)
    if paper:
        kw["strategy"] = "paper"
    seq = femreg.track(frames, **kw)
    g = seq[-1].on_grid()
    flags = [f for f in getattr(seq, "flags", []) if f]
    return {k: g[k] for k in _GRID_KEYS}, ("flagged: " + "; ".join(flags[:2])) if flags else ""


def _accumulate(frames, spacing, origin, fn):
    """Frame 0 -> last displacement from consecutive pairs, ``U_k(x) = U_{k-1}(x) + u_k(x + U_{k-1}(x))``,
    least-squares strain (3 mm window) of the accumulated field."""
    dx, dy = spacing
    shape = frames[0].shape
    I, J = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    U = np.zeros((2,) + shape)
    for k in range(1, len(frames)):
        r = fn(frames[k - 1], frames[k], spacing, origin)
        coords = [I + U[0] / dx, J + U[1] / dy]
        for c, key in enumerate(("ux", "uy")):
            inc = np.nan_to_num(r[key], nan=0.0)
            U[c] = U[c] + ndimage.map_coordinates(inc, coords, order=1, mode="nearest")
    e = peers.lsq_strain(U[0], U[1], spacing, (3.0 / dx + 1, 3.0 / dy + 1))
    return dict(ux=U[0], uy=U[1], **e)


def run_method(method, case, data):
    """(grids, message, seconds, CPU seconds) of ``method`` on ``data`` (a Pair or a SequencePair)."""
    paper = method == PAPER_METHOD
    t0, c0 = time.perf_counter(), time.process_time()
    msg = ""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if method in FEMREG_METHODS or paper:
            reg = FEMREG_METHODS.get(method, "momentum-stress")
            if case is not None and case.sequence:
                g, msg = _femreg_sequence(data.frames, data.spacing, data.origin, reg, paper)
            else:
                g, msg = _femreg_pair(data.ref, data.mov, data.spacing, data.origin, reg, paper)
        else:
            fn = PEER_METHODS[method]
            if case is not None and case.sequence:
                g = _accumulate(data.frames, data.spacing, data.origin, fn)
            else:
                g = fn(data.ref, data.mov, data.spacing, data.origin)
    return g, msg, time.perf_counter() - t0, time.process_time() - c0


# --------------------------------------------------------------------------------------------------------------
# Truth, ROI, metric
# --------------------------------------------------------------------------------------------------------------

def roi_slices(shape, spacing):
    """Pixel slices of the ROI: inset ``max(2 mm, 10 %)`` on every side, every ~0.1 mm axially."""
    sl = []
    for n, h in zip(shape, spacing):
        inset = int(math.ceil(max(2.0, 0.1 * n * h) / h))
        sl.append((inset, n - inset))
    step = max(1, int(round(0.1 / spacing[0])))
    return slice(sl[0][0], sl[0][1], step), slice(sl[1][0], sl[1][1])


def truth(data, case, sl, frame=None):
    """True fields on the ROI samples: dict of 2D arrays.  Sequences: frame 0 -> ``frame`` (default the last).
    ``case`` None: ``data`` is a pair (``forward.pairs.make_pair``)."""
    x0, y0 = data.origin
    dx, dy = data.spacing
    ii = np.arange(sl[0].start, sl[0].stop, sl[0].step)
    jj = np.arange(sl[1].start, sl[1].stop)
    X, Y = np.meshgrid(x0 + ii * dx, y0 + jj * dy, indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel()])
    if case is not None and case.sequence:
        k = len(data.frames) - 1 if frame is None else int(frame)
        u, e = data.true_displacement(k, P), data.true_strain(k, P)
    else:
        u, e = data.true_displacement(P), data.true_strain(P)
    sh = X.shape
    return dict(ux=u[:, 0].reshape(sh), uy=u[:, 1].reshape(sh), exx=e[:, 0].reshape(sh),
                eyy=e[:, 1].reshape(sh), exy=e[:, 2].reshape(sh))


def errors(g, t, sl, wavelength_mm) -> dict:
    """Relative L2 errors (fractions) over the ROI samples, hop fraction, coverage."""
    m = {k: np.asarray(g[k], float)[sl] for k in _GRID_KEYS}
    cover = float(np.mean(np.all([np.isfinite(m[k]) for k in _GRID_KEYS], axis=0)))
    m = {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in m.items()}

    def rel(keys, w=None):
        w = [1.0] * len(keys) if w is None else w
        num = sum(wi * np.sum((m[k] - t[k]) ** 2) for k, wi in zip(keys, w))
        den = sum(wi * np.sum(t[k] ** 2) for k, wi in zip(keys, w))
        return float(np.sqrt(num / den)) if den > 0 else float("nan")

    return dict(e=rel(("exx", "eyy", "exy"), (1.0, 1.0, 2.0)), exx=rel(("exx",)), eyy=rel(("eyy",)),
                ux=rel(("ux",)), uy=rel(("uy",)),
                hop=float(np.mean(np.abs(m["ux"] - t["ux"]) > 0.25 * wavelength_mm)), coverage=cover)


# --------------------------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------------------------

def draw_case(path, case, data, grids, results, t_full):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    shape = data.frames[0].shape if case.sequence else data.ref.shape
    dx, dy = data.spacing
    x0, y0 = data.origin
    ext = (y0 - dy / 2, y0 + (shape[1] - 0.5) * dy, x0 + (shape[0] - 0.5) * dx, x0 - dx / 2)
    tv = 100 * t_full["exx"]
    lo, hi = float(np.min(tv)), float(np.max(tv))
    pad = max(0.5 * abs(0.5 * (lo + hi)), 0.25 * (hi - lo), 0.05)
    vmin, vmax = lo - pad, hi + pad
    names = ["truth"] + [m for m in grids]
    n = len(names)
    ncol = min(n, 5)
    nrow = int(math.ceil(n / ncol))
    aspect = (ext[2] - ext[3]) / (ext[1] - ext[0])
    # at least 7.5 inches wide: the title of a one- or two-method picture fits
    fig, axes = plt.subplots(nrow, ncol, figsize=(max(2.6 * ncol, 7.5), 2.6 * aspect * nrow + 1.0), squeeze=False,
                             constrained_layout=True)
    sl = roi_slices(shape, data.spacing)
    r0, r1 = x0 + sl[0].start * dx, x0 + (sl[0].stop - 1) * dx
    c0, c1 = y0 + sl[1].start * dy, y0 + (sl[1].stop - 1) * dy
    im = None
    for ax, name in zip(axes.ravel(), names):
        if name == "truth":
            img, title = t_full["exx_img"], "truth"
        else:
            img = 100 * np.asarray(grids[name]["exx"], float)
            r = results[name]
            title = f"{name}\ne {100 * r['e']:.1f} %, {r['time_s']:.1f} s"
        im = ax.imshow(img, extent=ext, vmin=vmin, vmax=vmax, cmap="viridis", aspect="equal",
                       interpolation="nearest")
        ax.add_patch(Rectangle((c0, r0), c1 - c0, r1 - r0, fill=False, ec="w", lw=0.6, ls="--"))
        ax.set_title(title, fontsize=7)
        ax.tick_params(labelsize=6)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.6, label="axial strain e_xx (%)")
    fig.suptitle(f"{case.name}: {case.notes or getattr(data, 'name', '')} -- probe {case.probe}, "
                 f"{case.size_mm[0]}x{case.size_mm[1]} mm, SNR {case.snr_db} dB", fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches="tight")      # the colour bar's label whole however few panels
    plt.close(fig)


# --------------------------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------------------------

def make_data(case):
    field = case.field()
    if case is not None and case.sequence:
        return make_sequence(field, case.probe, case.size_mm, case.snr_db, case.seed, n_frames=10, step=0.01,
                             top_mm=case.top_mm, name=case.name)
    return make_pair(field, case.probe, case.size_mm, case.snr_db, case.seed, top_mm=case.top_mm, name=case.name)


def _full_truth_exx(data, case):
    shape = data.frames[0].shape if case.sequence else data.ref.shape
    x0, y0 = data.origin
    dx, dy = data.spacing
    step = max(1, shape[0] // 400)
    ii = np.arange(0, shape[0], step)
    X, Y = np.meshgrid(x0 + ii * dx, y0 + np.arange(shape[1]) * dy, indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel()])
    e = data.true_strain(len(data.frames) - 1, P) if case.sequence else data.true_strain(P)
    return np.repeat(100 * e[:, 0].reshape(X.shape), step, axis=0)[:shape[0]]


def _case_key(case, data, method) -> str:
    """Hash of everything a peer's result depends on: the case, the rendered pair's parameters, and the source of
    the simulator and of the peers."""
    src = "".join((Path(__file__).parent / f).read_text() for f in ("peers.py",)) + "".join(
        (ROOT / "forward" / f).read_text() for f in ("pairs.py", "fields.py", "ultrasound.py"))
    desc = dict(name=case.name, probe=case.probe, size=list(case.size_mm), snr=case.snr_db, top=case.top_mm,
                seed=case.seed, sequence=case.sequence, field=str(getattr(data, "name", "")),
                params=getattr(data, "params", None), method=method)
    return hashlib.sha256((json.dumps(desc, sort_keys=True, default=str) + src).encode()).hexdigest()[:16]


def _cache_load(cache, case, data, method):
    """(grids, message, seconds) of a peer from ``cache`` (a folder) or None.  femreg is never cached."""
    if cache is None or method not in PEER_METHODS:
        return None
    path = cache / f"{case.name}__{method.split()[0]}__{_case_key(case, data, method)}.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        return {k: z[k].astype(float) for k in _GRID_KEYS}, str(z["message"]), float(z["time_s"])


def _cache_save(cache, case, data, method, g, msg, dt):
    if cache is None or method not in PEER_METHODS:
        return
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"{case.name}__{method.split()[0]}__{_case_key(case, data, method)}.npz"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.npz")
    np.savez(tmp, message=np.str_(msg), time_s=np.float64(dt),
             **{k: np.asarray(g[k], np.float32) for k in _GRID_KEYS})
    os.replace(tmp, path)


def run(cases, methods, out: Path, progress=True, cache: Path | None = None):
    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    rows = []
    strategy = _has_strategy()
    csv_path = out / "results.csv"
    fields = ["case", "probe", "field", "size_mm", "snr_db", "method", "e", "exx", "eyy", "ux", "uy", "hop",
              "coverage", "time_s", "cpu_s", "message"]
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        bar = tqdm(cases, desc="cases", disable=not progress, file=sys.stderr)
        for case in bar:
            bar.set_postfix_str(case.name)
            t0 = time.perf_counter()
            data = make_data(case)
            t_sim = time.perf_counter() - t0
            shape = data.frames[0].shape if case.sequence else data.ref.shape
            sl = roi_slices(shape, data.spacing)
            t = truth(data, case, sl)
            lam = PROBES[case.probe].wavelength_mm
            grids, results = {}, {}
            for method in methods:
                if method == PAPER_METHOD and not strategy and "R_P_sigma" in results:
                    g = grids["R_P_sigma"]
                    r = dict(results["R_P_sigma"], message="same run as R_P_sigma (its default is the paper's)")
                else:
                    try:
                        cached = _cache_load(cache, case, data, method)
                        if cached is not None:
                            (g, msg, dt), cpu = cached, float("nan")
                        else:
                            g, msg, dt, cpu = run_method(method, case, data)
                            _cache_save(cache, case, data, method, g, msg, dt)
                        r = errors(g, t, sl, lam)
                    except Exception as exc:  # noqa: BLE001 -- a failing method is a result of the benchmark
                        g, msg, dt, cpu = {k: np.full(shape, np.nan) for k in _GRID_KEYS}, \
                            f"error: {type(exc).__name__}: {exc}"[:200], float("nan"), float("nan")
                        r = dict(e=float("nan"), exx=float("nan"), eyy=float("nan"), ux=float("nan"),
                                 uy=float("nan"), hop=float("nan"), coverage=0.0)
                    r.update(time_s=dt, cpu_s=cpu, message=msg)
                grids[method], results[method] = g, r
                row = dict(case=case.name, probe=case.probe, field=case.notes or getattr(data, "name", ""),
                           size_mm=f"{case.size_mm[0]}x{case.size_mm[1]}", snr_db=case.snr_db, method=method,
                           **{k: (f"{v:.5g}" if isinstance(v, float) else v) for k, v in r.items()})
                w.writerow(row)
                fh.flush()
                rows.append(dict(row, **r))
            t_full = dict(exx=_full_truth_exx(data, case))
            t_full["exx_img"] = t_full["exx"]
            t_full["exx"] = t_full["exx"] / 100
            draw_case(out / f"{case.name}.png", case, data, grids, results, t_full)
            print(f"# {case.name}: simulated in {t_sim:.1f} s; " + ", ".join(
                f"{m} {100 * results[m]['e']:.1f}%/{results[m]['time_s']:.1f}s" for m in methods), file=sys.stderr)
    md = tables(rows, cases, methods, strategy)
    (out / "results.md").write_text(md)
    print(md)
    return rows


def _fmt(r):
    if not np.isfinite(r["e"]):
        return "failed"
    s = f"{100 * r['e']:.1f}"
    if r["hop"] > 0.01:
        s += f" (hop {100 * r['hop']:.0f}%)"
    return s


def compare(old_csv, new_csv) -> str:
    """Markdown table: total strain error (%) of every femreg method in ``old_csv`` -> ``new_csv`` per case, with
    the best peer of the new run (the peers do not depend on femreg)."""
    def load(path):
        with open(path, newline="") as fh:
            return {(r["case"], r["method"]): r for r in csv.DictReader(fh)}

    old, new = load(old_csv), load(new_csv)
    cases = list(dict.fromkeys(c for c, _ in new))
    fem = [m for m in list(FEMREG_METHODS) + [PAPER_METHOD] if any((c, m) in new for c in cases)]

    def e(d, key):
        try:
            return 100 * float(d[key]["e"])
        except (KeyError, ValueError):
            return float("nan")

    out = ["| case | " + " | ".join(fem) + " | best peer |\n", "|---|" + "---|" * (len(fem) + 1) + "\n"]
    for c in cases:
        cells = [f"{e(old, (c, m)):.1f} -> **{e(new, (c, m)):.1f}**" for m in fem]
        peers_e = [(e(new, (c, m)), m) for m in PEER_METHODS if (c, m) in new]
        peers_e = [p for p in peers_e if np.isfinite(p[0])]
        best = min(peers_e) if peers_e else (float("nan"), "")
        out.append(f"| {c} | " + " | ".join(cells) + f" | {best[0]:.1f} ({best[1]}) |\n")
    return "## Total strain error %, before -> after\n\n" + "".join(out)


def tables(rows, cases, methods, strategy) -> str:
    by = {(r["case"], r["method"]): r for r in rows}
    names = [c.name for c in cases]
    head = "| case | " + " | ".join(methods) + " |\n|---|" + "---|" * len(methods) + "\n"
    lines = ["## Total strain error % (hop: pixels with |u_x error| > wavelength/4)\n", head]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(_fmt(by[(n, m)]) if (n, m) in by else "" for m in methods) + " |\n")
    lines += ["\n## Axial strain error % (e_xx only)\n", head]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(
            f"{100 * by[(n, m)]['exx']:.1f}" if (n, m) in by and np.isfinite(by[(n, m)]["exx"]) else ""
            for m in methods) + " |\n")
    lines += ["\n## Axial / lateral displacement error % (u_x / u_y)\n", head]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(
            f"{100 * by[(n, m)]['ux']:.2f} / {100 * by[(n, m)]['uy']:.1f}" if (n, m) in by and np.isfinite(
                by[(n, m)]["ux"]) else "" for m in methods) + " |\n")
    lines += ["\n## Wall time s (1 thread)\n", head]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(
            f"{by[(n, m)]['time_s']:.2f}" if (n, m) in by and np.isfinite(by[(n, m)]["time_s"]) else ""
            for m in methods) + " |\n")
    lines += ["\n## CPU time s (of this process; empty: cached peer)\n", head]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(
            f"{by[(n, m)]['cpu_s']:.2f}" if (n, m) in by and np.isfinite(by[(n, m)].get("cpu_s", np.nan)) else ""
            for m in methods) + " |\n")
    notes = [f"- {r['case']} / {r['method']}: {r['message']}" for r in rows
             if r.get("message") and not r["message"].startswith("same run")]
    if notes:
        lines += ["\nMessages:\n"] + [n + "\n" for n in notes]
    if not strategy:
        lines.append("\n`register` has no `strategy` option here: its default procedure is the paper's, so "
                     f"'{PAPER_METHOD}' repeats R_P_sigma.\n")
    return "".join(lines)


def parse_refine(text):
    """``--refine`` text -> ``refine=`` of femreg's pairs (:data:`REFINE`): none / 0, auto or a number of passes."""
    return None if text in ("none", "0") else (text if text == "auto" else int(text))


def select_cases(cases, words: str) -> list:
    """The cases whose name contains one of the comma-separated ``words`` (all for "")."""
    ws = [w for w in words.split(",") if w]
    return [c for c in cases if not ws or any(w in c.name for w in ws)]


def select_methods(words: str, methods=None) -> list:
    """The methods (default :data:`ALL_METHODS`) named by the comma-separated ``words``: a method's full name
    selects it alone, any other word every method whose name contains it ("": all)."""
    methods = list(ALL_METHODS if methods is None else methods)
    ws = [w for w in words.split(",") if w]
    return [m for m in methods if not ws or any(w == m or (w not in ALL_METHODS and w in m) for w in ws)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the quick subset (6 cases)")
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--methods", default="", help="comma-separated words; run methods whose name contains one "
                                                   "(a method's full name: that method only)")
    ap.add_argument("--out", default="out/robustness", help="output folder (default out/robustness)")
    ap.add_argument("--list", action="store_true", help="list the cases and methods and exit")
    ap.add_argument("--compare", metavar="OLD_CSV",
                    help="after the run (or alone with --no-run), print femreg's total strain errors of OLD_CSV -> "
                         "this run side by side with the best peer (written to <out>/compare.md)")
    ap.add_argument("--no-run", action="store_true", help="with --compare: compare <out>/results.csv only")
    ap.add_argument("--seed", type=int, default=0,
                    help="added to every case's seed: other speckle and noise realisations of the same matrix")
    ap.add_argument("--refine", default=None,
                    help="refine= of femreg's pair registrations (not the paper's procedure): none, auto or a number "
                         "of passes; default: register's own default")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--no-cache", action="store_true",
                    help="recompute the peers (by default their results are cached in <out>/peer_cache, keyed by "
                         "the case and the source of the simulator and the peers; femreg always runs)")
    a = ap.parse_args(argv)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    if a.refine is not None:
        global REFINE
        REFINE = parse_refine(a.refine)
    cases = select_cases([c for c in CASES if c.quick] if a.quick else CASES, a.cases)
    if a.seed:
        cases = [dataclasses.replace(c, seed=c.seed + a.seed) for c in cases]
    methods = select_methods(a.methods)
    if a.list:
        for c in CASES:
            print(f"{c.name:24s} probe {c.probe:5s} {c.size_mm[0]}x{c.size_mm[1]} mm SNR {c.snr_db} dB"
                  f"{' [quick]' if c.quick else ''} {c.notes}")
        print("methods:", ", ".join(ALL_METHODS))
        return 0
    if not cases or not methods:
        print("no case or method selected (see --list)", file=sys.stderr)
        return 2
    out = Path(a.out)
    if not a.no_run:
        t0 = time.perf_counter()
        run(cases, methods, out, progress=not a.no_progress, cache=None if a.no_cache else out / "peer_cache")
        print(f"\ntotal {time.perf_counter() - t0:.0f} s, {len(cases)} cases x {len(methods)} methods")
    if a.compare:
        md = compare(a.compare, out / "results.csv")
        (out / "compare.md").write_text(md)
        print("\n" + md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
