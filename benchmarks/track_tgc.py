"""``femreg.track`` and ``femreg.elastogram`` on a loop whose receiver noise a time-gain compensation lifts to the
echo's level at depth (:func:`forward.pairs.make_sequence` with ``echo_gain_db`` = attenuation and ``tgc_db`` its
inverse: the level is flat to the bottom, the echo meets the noise at ``floor`` mm).

The level rule (:func:`femreg.echo.find_echo`) sees nothing; :func:`femreg.register` cuts the rows of block-matching
windows that find no match (:func:`femreg.echo.unmatched_crop`).  ``track`` and ``elastogram`` decide one crop for
the loop: from frames 0 and 1 (the first two that differ) they now make the same cut.  Three runs of each: the
loop as given, and the loop cut by hand at ``floor`` (``roi=None`` on the rows above it).

Scores: track, total strain error (%, e_xy weighted 2) of frame 0 -> k over the echo (the box both meshes cover,
less 3 mm above the floor), elements, flags, wall time; elastogram, RMS of the normalised axial strain error (%,
truth of the best frame's pair normalised the same way) over the same box, pairs usable, wall time.

Measured (seeds 0-1, 2026-12-07): track before meshed the noise (L7 / paper / L12: 2624 / 2436 / 3690 elements),
12.8-17.8 % / 7.3-13.3 % / 18.1-59.6 % (L12 frames 2-3 failed); now cut at 22.9-24.2 / 33.3-35.0 / 12.4-13.9 mm,
7.4-8.3 % / 7.7-10.5 % / 0.3-1.7 % on 380-460 / 462-483 / 195-361 elements, the hand cut 7.4-7.9 % / 7.4-8.6 % /
0.6-2.3 %.  Elastogram: within 0.1 points of the hand cut (before 10.7 / 8.4 % against 6.7 / 6.8 % on L7, one or
no usable pair on L12).

Run: ``python benchmarks/track_tgc.py [--cases L7 L12 paper] [--seeds 0 1] [--what track elastogram]`` (about
1 min for all on one core).  ``PYTHONPATH`` chooses the code measured (``PYTHONPATH=. python ...`` this tree's).
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))      # after PYTHONPATH: it chooses the femreg measured

import femreg  # noqa: E402
from femreg.elastogram import elastogram  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import (PROBES, alpha_for_floor, attenuation_gain_db, box_points, make_sequence,  # noqa: E402
                           total_strain_error)

SNR, TOP = 30.0, 2.0
#: name: probe, (depth, width) mm, floor mm, field, frames, step per frame
CASES = {
    "L7": ("L7", (30.0, 20.0), 24.0, lambda: F.Inclusion("stiff", "plane-strain", 0.01, radius_mm=3.0), 4, 0.01),
    "L12": ("L12", (20.0, 12.0), 15.0, lambda: F.compression(0.01), 4, 0.01),
    "paper": ("paper", (40.0, 30.0), 34.0, lambda: F.Inclusion("stiff", "plane-strain", 0.01, radius_mm=3.0), 4,
              0.01),
}


def tgc_loop(name, seed=0):
    probe, size, floor, field, n, step = CASES[name]
    pr = PROBES[probe]
    gain = attenuation_gain_db(alpha_for_floor(floor, SNR, pr.f0_mhz), pr.f0_mhz)
    s = make_sequence(field(), probe, size, SNR, seed, n_frames=n, step=step, top_mm=TOP, echo_gain_db=gain,
                      tgc_db=lambda x: -gain(x))
    return s, floor


def total_error(res, s, k, box, step=2):
    P = box_points(s.frames.shape[1:], s.spacing, s.origin, box, step)
    e, est = s.true_strain(k, P), res.strain(P)
    ok = np.all(np.isfinite(est), axis=1)
    return total_strain_error(est[ok], e[ok]), ok.mean()


def _box(meshes, floor):
    lo = max(m.p[0].min() for m in meshes)
    hi = min(min(m.p[0].max() for m in meshes), floor - 3.0)
    return lo, hi, max(m.p[1].min() for m in meshes), min(m.p[1].max() for m in meshes)


def run_track(s, floor):
    n = int(round((floor - s.origin[0]) / s.spacing[0])) + 1
    out = {}
    for how, frames, kw in (("auto", s.frames, {}), ("hand", s.frames[:, :n], dict(roi=None))):
        t = time.perf_counter()
        out[how] = femreg.track(frames, spacing=s.spacing, origin=s.origin, **kw)
        out[how].wall = time.perf_counter() - t
    box = _box([out["auto"][0].mesh, out["hand"][0].mesh], floor)
    for how, seq in out.items():
        errs = [total_error(r, s, k, box)[0] for k, r in enumerate(seq, start=1)]
        cut = seq[0].roi[1] if getattr(seq[0], "roi", None) is not None else float("nan")
        print(f"  track {how:5s} elements {seq[0].mesh.t.shape[1]:6d}  cut {cut:5.1f} mm  error/frame "
              + " ".join(f"{e:6.2f}" for e in errs) + f" %  success {[bool(r.success) for r in seq]}  "
              f"flags {sum(bool(f) for f in seq.flags)}  wall {seq.wall:6.1f} s")
        if how == "auto" and seq[0].excluded:
            print(f"    excluded: {seq[0].excluded}")
    return out


def run_elastogram(s, floor):
    n = int(round((floor - s.origin[0]) / s.spacing[0])) + 1
    for how, frames, kw in (("auto", s.frames, {}), ("hand", s.frames[:, :n], dict(roi=None))):
        t = time.perf_counter()
        res = elastogram(frames, spacing=s.spacing, origin=s.origin, **kw)
        wall = time.perf_counter() - t
        (r0, r1), (c0, c1) = res.region if res.region is not None else ((0, frames.shape[1]), (0, frames.shape[2]))
        x = s.origin[0] + np.arange(r0, r1) * s.spacing[0]
        y = s.origin[1] + np.arange(c0, c1) * s.spacing[1]
        X, Y = np.meshgrid(x, y, indexing="ij")
        P = np.column_stack([X.ravel(), Y.ravel()])
        i = res.ref_frame
        usable = sum(bool(r["usable"]) for r in res.pairs)
        j = next((r["mov"] for r in res.pairs if r["ref"] == i and r["usable"]), None)
        if j is None:
            print(f"  elastogram {how:5s} region rows {r0}-{r1}  nothing usable  wall {wall:6.1f} s")
            continue
        # the pair's strain frame i -> j at frame-i points: small strain, difference of the frame-0 fields
        true = (s.true_strain(j, P)[:, 0] - s.true_strain(i, P)[:, 0]).reshape(X.shape)
        est = res.exx
        inside = (X >= 4.0) & (X <= floor - 3.0)
        ok = np.isfinite(est) & inside
        err = 100 * float(np.sqrt(np.mean((est[ok] / np.mean(est[ok]) - true[ok] / np.mean(true[ok])) ** 2)))
        print(f"  elastogram {how:5s} region rows {r0}-{r1}  normalised error {err:6.2f} % over "
              f"{ok.sum() / max(inside.sum(), 1):.2f} of the echo  pairs usable {usable}  wall {wall:6.1f} s")
        if how == "auto" and res.excluded:
            print(f"    excluded: {res.excluded}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--what", nargs="*", default=["track", "elastogram"])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0])
    a = ap.parse_args(argv)
    print(f"femreg from {Path(femreg.__file__).parent}")
    for name, seed in ((c, sd) for c in a.cases for sd in a.seeds):
        s, floor = tgc_loop(name, seed)
        print(f"{name} seed {seed}: frames {s.frames.shape}, floor {floor} mm")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            if "track" in a.what:
                run_track(s, floor)
            if "elastogram" in a.what:
                run_elastogram(s, floor)


if __name__ == "__main__":
    main()
