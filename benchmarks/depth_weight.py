"""eq:IR weighted by the residual's variance at each depth (maximum likelihood, iteratively reweighted) against
register's default, on the pairs an echo that falls with depth concerns and on pairs whose echo is level.

The weighting (measured, not adopted: docs/robustness.md, "An echo that falls with depth"; :func:`weighted`
installs it around :func:`femreg.register`): after register's unrefined solve (its lambda_bar stage), each image
row's weight in eq:IR becomes ``1 / sigma^2(x)``, ``sigma^2`` the median of the image residual
``r^2 = (I_2(x + u) - I_1(x))^2`` (normalised frames) over that row, averaged over 2 mm of depth
(:func:`depth_weights`), scaled by ``--norm``: "mean" (mean weight 1 over the registered pixels), "variance"
(``mean sigma^2 / sigma^2``: the unweighted term's single variance kept) or "geometric" (geometric mean 1); the
final mesh is solved again from the solution (``--passes`` times, reweighted each time) and then refined as usual,
the weights reaching the refined solves too.  Under speckle decorrelation the residual scales with the echo power
(the weights level the echo), under receiver noise it is flat (they do not).

Sections (``--sections``):

* ``fine``: the 15 MHz fine-pitch no-TGC pair of ``benchmarks/fine_pitch_alpha.py`` (seed 7) and its 7.5 MHz
  variant: strain ratio (true in brackets), slide (um), e_xx and total strain error (%) as measured there;
* ``floor``: the 12 noise-floor pairs of ``benchmarks/refine_noise_floor.py``: total strain error (%) as scored
  there;
* ``robust``: ``benchmarks/robustness.py``'s pairs (seed 0, R_P_sigma, no sequence case): total strain error (%);
* ``invivo``: consecutive pairs of the two in vivo sequences: NCC after, success; ``--pictures DIR`` writes the
  axial strain of default and weighted side by side per pair.

Measured (2026-12-07, one core of a shared 2-core machine, about 7 min; docs/robustness.md, "An echo that falls with
depth"): the 15 MHz nodule's strain ratio 1.01 -> 1.01 ("mean") / 1.04 ("variance"), true 2.14, the weights at
3 / 16 / 22 mm 0.30 / 1.55 / 2.03 and 0.95 / 4.89 / 6.43; at 7.5 MHz 1.03 -> 1.03, weights 0.97-1.15; floor pairs
-0.93 .. +0.02 points ("mean", the failed rotated pair 543.87 -> 547.72 %), robustness pairs -0.77 .. +0.12; in vivo
seq304 1 -> 2 and 3 -> 4 refined (8700 / 8526 elements against 1380) with streaks and columns at depth.  Not adopted.

Run: ``OMP_NUM_THREADS=1 python benchmarks/depth_weight.py [--sections fine,floor,robust,invivo] [--passes 1]``.
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import contextlib

import numpy as np
from scipy.ndimage import uniform_filter1d

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import femreg  # noqa: E402


SMOOTH_MM = 2.0          # depth over which the per-row residual level is averaged (a few pulse lengths)


def depth_weights(term, u, n_rows, spacing_x, norm="mean"):
    """(n_rows,) weights of the image rows: ``1 / sigma^2``, ``sigma^2`` the median of ``r^2`` over each row's
    pixels of ``term`` (:class:`femreg.data_term.SSDTerm`, weight > 0) at ``u``, averaged over :data:`SMOOTH_MM`;
    rows without a pixel take the nearest row's value; scaled as ``norm`` says (module docstring)."""
    quad = term.quad
    r = np.asarray(term.residual(u), float)
    keep = np.asarray(term.w) > 0
    rows, r2 = (quad.index // quad.shape[1])[keep], np.square(r[keep])
    order = np.lexsort((r2, rows))
    rows, r2 = rows[order], r2[order]
    present, start, count = np.unique(rows, return_index=True, return_counts=True)
    med = np.array([np.median(r2[s:s + c]) for s, c in zip(start, count)])
    sig = uniform_filter1d(np.interp(np.arange(n_rows), present, med), max(1, int(round(SMOOTH_MM / spacing_x))),
                           mode="nearest")
    sig = np.maximum(sig, 1e-12 * float(sig.max()))
    w, c = 1.0 / sig, count / count.sum()
    if norm == "variance":
        return w * float(np.sum(sig[present] * c))
    if norm == "geometric":
        return w / float(np.exp(np.sum(np.log(w[present]) * c)))
    return w / float(np.sum(w[present] * c))


@contextlib.contextmanager
def weighted(passes=1, norm="mean"):
    """Within: :func:`femreg.register` re-solves its unrefined solution with eq:IR weighted by
    :func:`depth_weights` (``passes`` times, reweighted each time) before refining (module docstring)."""
    import femreg.gnsolve as G
    import femreg.registration as R

    term0, stage0 = G.image_term, R.lambda_bar_stage

    def image_term(I1, I2, mesh, shape, spacing, origin, **kw):
        term = term0(I1, I2, mesh, shape, spacing, origin, **kw)
        term.reference_image = I1
        rw = getattr(I1, "row_weights", None)
        if rw is not None:
            term.w = term.w * rw[term.quad.index // term.quad.shape[1]]
        return term

    def stage(sol, user_reg, notes, resolve, *, follows):
        marked, sol = stage0(sol, user_reg, notes, resolve, follows=follows)
        I1, q = sol.data.reference_image, sol.data.quad
        for _ in range(passes):
            I1.row_weights = depth_weights(sol.data, sol.u, q.shape[0], float(q.spacing[0]), norm)
            LAST.update(weights=I1.row_weights, origin=float(q.origin[0]), dx=float(q.spacing[0]))
            sol = resolve(sol.u)
        return marked, sol

    G.image_term, R.lambda_bar_stage = image_term, stage
    try:
        yield
    finally:
        G.image_term, R.lambda_bar_stage = term0, stage0


#: The row weights of the last weighted solve, with the image's depth origin and spacing (mm).
LAST = {}
#: ``[factor]``: the floor and robust sections add the default with R_P_sigma's alpha times it (``--alpha-factor``)
ALPHA_FACTOR = []
#: (passes, norm) of the weighted runs (``--passes``, ``--norm``)
WEIGHTING = [1, "mean"]


def _reg(ref, mov, sp, org, depth_weight=False, **kw):
    """:func:`femreg.register` with its defaults, or weighted (:func:`weighted`); (result, seconds)."""
    with warnings.catch_warnings(), (weighted(*WEIGHTING) if depth_weight else contextlib.nullcontext()):
        warnings.simplefilter("ignore")
        t = time.perf_counter()
        res = femreg.register(ref, mov, spacing=sp, origin=org, **kw)
        return res, time.perf_counter() - t


def fine(passes):
    from benchmarks.fine_pitch_alpha import L7, make_pair, measure

    print("| pair | weighting | SR (true) | slide um (true) | e_xx % | total % | outside band % | fat % | weight at "
          "3 / 16 / 22 mm | s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, pk in (("15 MHz, 0.1 mm pitch, no TGC", {}), ("7.5 MHz, 0.2 mm pitch, no TGC", L7)):
        ref, mov, sp, org, truth = make_pair(seed=7, **pk)
        for label, kw in (("default", {}), (f"depth weight x{passes}", {"depth_weight": passes})):
            LAST.clear()
            res, dt = _reg(ref, mov, sp, org, **kw)
            m = measure(res, truth, 2.0, 25.6)
            w = " / ".join(f"{LAST['weights'][int(round((x - LAST['origin']) / LAST['dx']))]:.2f}"
                           for x in (3.0, 16.0, 22.0)) if LAST else "1"
            print(f"| {name} | {label} | {m['sr']:.2f} ({m['sr_true']:.2f}) | {m['slide']:.1f} ({m['slide_true']:.1f})"
                  f" | {m['exx']:.1f} | {m['total']:.1f} | {m['outside']:.1f} | {m['fat']:.1f} | {w} | {dt:.0f} |",
                  flush=True)


def _control(kw):
    """``kw`` with R_P_sigma's alpha times ``--alpha-factor`` (the control: a global change of the balance)."""
    from femreg.regularizers import make_regularizer

    return dict(kw, alpha=ALPHA_FACTOR[0] * make_regularizer("momentum-stress").alpha)


def floor(passes, words=()):
    from benchmarks.refine_noise_floor import CASES, _scored, make_floor_pair
    from benchmarks.robustness import roi_slices, truth

    ctl = f" default, alpha x {ALPHA_FACTOR[0]:g} % |" if ALPHA_FACTOR else ""
    print(f"| pair | default % | depth weight % | change | success default / weighted |{ctl}")
    print("|---|---|---|---|---|" + "---|" * bool(ctl))
    for case in CASES:
        if words and not any(w in case.name for w in words):
            continue
        data, mov, pr = make_floor_pair(case)
        sl = roi_slices(data.ref.shape, data.spacing)
        t = truth(data, None, sl)
        out = []
        for kw in ({}, {"depth_weight": passes}) + ((_control({}),) if ALPHA_FACTOR else ()):
            res, _ = _reg(data.ref, mov, data.spacing, data.origin, **kw)
            out.append((_scored(res, t, sl, pr.wavelength_mm), res.success))
        extra = f" {out[2][0]:.2f} |" if ALPHA_FACTOR else ""
        print(f"| {case.name} | {out[0][0]:.2f} | {out[1][0]:.2f} | {out[1][0] - out[0][0]:+.2f} "
              f"| {out[0][1]} / {out[1][1]} |{extra}", flush=True)


def robust(passes, words=()):
    from benchmarks.robustness import CASES, errors, make_data, roi_slices, truth
    from femreg.image import depth_trend_db
    from forward.pairs import PROBES

    ctl = f" default, alpha x {ALPHA_FACTOR[0]:g} % |" if ALPHA_FACTOR else ""
    print(f"| pair | fall (dB) | default % | depth weight % | change |{ctl}")
    print("|---|---|---|---|---|" + "---|" * bool(ctl))
    for case in CASES:
        if case.sequence or (words and not any(w in case.name for w in words)):
            continue
        data = make_data(case)
        sl = roi_slices(data.ref.shape, data.spacing)
        t = truth(data, case, sl)
        tr = depth_trend_db(data.ref, data.spacing)
        wl = PROBES[case.probe].wavelength_mm
        e = []
        for kw in ({}, {"depth_weight": passes}) + ((_control({}),) if ALPHA_FACTOR else ()):
            res, _ = _reg(data.ref, data.mov, data.spacing, data.origin, **kw)
            e.append(100 * errors(res.on_grid(), t, sl, wl)["e"])
        extra = f" {e[2]:.2f} |" if ALPHA_FACTOR else ""
        print(f"| {case.name} | {tr[0] - tr[-1]:.1f} | {e[0]:.2f} | {e[1]:.2f} | {e[1] - e[0]:+.2f} |{extra}",
              flush=True)


def invivo(passes, pictures=None, pairs=None):
    import importlib.util

    spec = importlib.util.spec_from_file_location("demo07", ROOT / "demos" / "07_invivo.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    data = demo.data_dir()
    if data is None:
        print("in vivo data not found: skipped")
        return
    print("| pair | NCC after default / weighted | success | elements | mean |e_xx| % at 20-30 mm default / "
          "weighted | s |")
    print("|---|---|---|---|---|---|")
    for seq in ("seq299", "seq304"):
        frames, sp, org = demo.load_sequence(data / seq)
        for k in (pairs or range(len(frames) - 1)):
            rs = []
            for kw in ({}, {"depth_weight": passes}):
                rs.append(_reg(frames[k], frames[k + 1], sp, org, **kw))
            exx = [r.on_grid()["exx"] for r, _ in rs]
            depth = org[0] + np.arange(frames.shape[1]) * sp[0]
            band = (depth > 20) & (depth < 30)
            deep = [100 * float(np.nanmean(np.abs(e[band]))) if np.isfinite(e[band]).any() else float("nan")
                    for e in exx]
            print(f"| {seq} {k + 1}->{k + 2} | {rs[0][0].ncc_after:.3f} / {rs[1][0].ncc_after:.3f} "
                  f"| {rs[0][0].success} / {rs[1][0].success} | {rs[0][0].mesh.t.shape[1]} / {rs[1][0].mesh.t.shape[1]}"
                  f" | {deep[0]:.2f} / {deep[1]:.2f} | {rs[0][1]:.0f} / {rs[1][1]:.0f} |", flush=True)
            if pictures:
                _picture(Path(pictures) / f"{seq}_{k + 1}_{k + 2}.png", exx, sp, org, f"{seq} {k + 1}->{k + 2}")


def _picture(path, exx, sp, org, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    ext = [org[1], org[1] + exx[0].shape[1] * sp[1], org[0] + exx[0].shape[0] * sp[0], org[0]]
    lim = np.nanpercentile(np.abs(100 * exx[0]), 98)
    fig, ax = plt.subplots(1, 2, figsize=(9, 6), sharey=True)
    for a, e, lab in zip(ax, exx, ("default", "depth weight")):
        im = a.imshow(100 * e, extent=ext, cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
        a.set_title(f"{title}: {lab}")
        a.set_xlabel("lateral (mm)")
    ax[0].set_ylabel("depth (mm)")
    fig.colorbar(im, ax=ax, label="e_xx %")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sections", default="fine,floor,robust,invivo")
    ap.add_argument("--passes", type=int, default=1, help="re-solves, reweighted each time (default 1)")
    ap.add_argument("--cases", default="", help="comma-separated words: floor / robust pairs whose name holds one")
    ap.add_argument("--pairs", default="", help="in vivo pair indices (0 = frames 1 -> 2), comma-separated")
    ap.add_argument("--pictures", default=None, help="folder for the in vivo strain pictures")
    ap.add_argument("--alpha-factor", type=float, default=None,
                    help="floor / robust: also the default with R_P_sigma's alpha times this (a control)")
    ap.add_argument("--norm", default="mean", help="mean | variance | geometric (module docstring)")
    a = ap.parse_args(argv)
    WEIGHTING[:] = [a.passes, a.norm]
    ALPHA_FACTOR[:] = [a.alpha_factor] if a.alpha_factor else []
    words = [w for w in a.cases.split(",") if w]
    pairs = [int(p) for p in a.pairs.split(",") if p] or None
    print(f"femreg {femreg.__version__} from {Path(femreg.__file__).parent}; norm {a.norm}, passes {a.passes}")
    for s in a.sections.split(","):
        print(f"\n## {s}\n")
        if s == "fine":
            fine(a.passes)
        elif s == "floor":
            floor(a.passes, words)
        elif s == "robust":
            robust(a.passes, words)
        elif s == "invivo":
            invivo(a.passes, a.pictures, pairs)


if __name__ == "__main__":
    main()
