"""eq:IR weighted by the residual's variance at each depth (maximum likelihood, one re-solve) against register's
default, on the pairs an echo that falls with depth concerns and on pairs whose echo is level.

``register(..., depth_weight=k)``: after the unrefined solve, each image row's weight in eq:IR is ``1 / sigma^2``,
``sigma^2`` the median of the image residual ``r^2`` over that row smoothed over 2 mm of depth
(:func:`femreg.data_term.depth_weights`), normalised to mean 1 over the registered pixels; the final mesh solved
again from the solution (``k`` times, reweighted each time), then refined as usual.

Sections (``--sections``):

* ``fine``: the 15 MHz fine-pitch no-TGC pair of ``benchmarks/fine_pitch_alpha.py`` (seed 7) and its 7.5 MHz
  variant: strain ratio (true in brackets), slide (um), e_xx and total strain error (%) as measured there;
* ``floor``: the 12 noise-floor pairs of ``benchmarks/refine_noise_floor.py``: total strain error (%) as scored
  there;
* ``robust``: ``benchmarks/robustness.py``'s pairs (seed 0, R_P_sigma, no sequence case): total strain error (%);
* ``invivo``: consecutive pairs of the two in vivo sequences: NCC after, success; ``--pictures DIR`` writes the
  axial strain of default and weighted side by side per pair.

Run: ``OMP_NUM_THREADS=1 python benchmarks/depth_weight.py [--sections fine,floor,robust,invivo] [--passes 1]``.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import femreg  # noqa: E402


def _reg(ref, mov, sp, org, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = time.perf_counter()
        res = femreg.register(ref, mov, spacing=sp, origin=org, **kw)
        return res, time.perf_counter() - t


def fine(passes):
    from benchmarks.fine_pitch_alpha import L7, make_pair, measure

    print("| pair | weighting | SR (true) | slide um (true) | e_xx % | total % | outside band % | fat % | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, pk in (("15 MHz, 0.1 mm pitch, no TGC", {}), ("7.5 MHz, 0.2 mm pitch, no TGC", L7)):
        ref, mov, sp, org, truth = make_pair(seed=7, **pk)
        for label, kw in (("default", {}), (f"depth weight x{passes}", {"depth_weight": passes})):
            res, dt = _reg(ref, mov, sp, org, **kw)
            m = measure(res, truth, 2.0, 25.6)
            print(f"| {name} | {label} | {m['sr']:.2f} ({m['sr_true']:.2f}) | {m['slide']:.1f} ({m['slide_true']:.1f})"
                  f" | {m['exx']:.1f} | {m['total']:.1f} | {m['outside']:.1f} | {m['fat']:.1f} | {dt:.0f} |",
                  flush=True)


def floor(passes, words=()):
    from benchmarks.refine_noise_floor import CASES, _scored, make_floor_pair
    from benchmarks.robustness import roi_slices, truth

    print("| pair | default % | depth weight % | change | success default / weighted |")
    print("|---|---|---|---|---|")
    for case in CASES:
        if words and not any(w in case.name for w in words):
            continue
        data, mov, pr = make_floor_pair(case)
        sl = roi_slices(data.ref.shape, data.spacing)
        t = truth(data, None, sl)
        out = []
        for kw in ({}, {"depth_weight": passes}):
            res, _ = _reg(data.ref, mov, data.spacing, data.origin, **kw)
            out.append((_scored(res, t, sl, pr.wavelength_mm), res.success))
        print(f"| {case.name} | {out[0][0]:.2f} | {out[1][0]:.2f} | {out[1][0] - out[0][0]:+.2f} "
              f"| {out[0][1]} / {out[1][1]} |", flush=True)


def robust(passes, words=()):
    from benchmarks.robustness import CASES, errors, make_data, roi_slices, truth
    from femreg.image import depth_trend_db
    from forward.pairs import PROBES

    print("| pair | fall (dB) | default % | depth weight % | change |")
    print("|---|---|---|---|---|")
    for case in CASES:
        if case.sequence or (words and not any(w in case.name for w in words)):
            continue
        data = make_data(case)
        sl = roi_slices(data.ref.shape, data.spacing)
        t = truth(data, case, sl)
        tr = depth_trend_db(data.ref, data.spacing)
        wl = PROBES[case.probe].wavelength_mm if case.probe in PROBES else 0.2
        e = []
        for kw in ({}, {"depth_weight": passes}):
            res, _ = _reg(data.ref, data.mov, data.spacing, data.origin, **kw)
            e.append(100 * errors(res.on_grid(), t, sl, wl)["e"])
        print(f"| {case.name} | {tr[0] - tr[-1]:.1f} | {e[0]:.2f} | {e[1]:.2f} | {e[1] - e[0]:+.2f} |", flush=True)


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
    ap.add_argument("--norm", default="mean", help="femreg.data_term.DEPTH_WEIGHT_NORM")
    a = ap.parse_args(argv)
    import femreg.data_term
    femreg.data_term.DEPTH_WEIGHT_NORM = a.norm
    words = [w for w in a.cases.split(",") if w]
    pairs = [int(p) for p in a.pairs.split(",") if p] or None
    print(f"femreg from {Path(femreg.__file__).parent}; norm {a.norm}, passes {a.passes}")
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
