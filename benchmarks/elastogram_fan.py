"""``femreg.elastogram`` on a freehand loop shown as a convex probe's display: 8-bit B-mode inside a fan whose
black wedges are fixed on the screen (forward.freehand, L7, 14 x 12 mm, the fan's apex 8 mm above the first row,
74 % of the frame; the loop of tests/test_elastogram.py).

Prints, per seed: the pairs usable, the fraction of the fan with a finite elastogram, the normalised strain error
(RMS of estimated minus true axial strain, each divided by its mean over the covered pixels less 10 % of the
depth at the top and bottom, percent; as tests/test_elastogram.py), the same error on the pixels of the largest
rectangle without fill only, and the wall time.  The result is placed on the full frames through ``region``, so
the script runs on the code before the whole fan was used as well (it registered that rectangle).

Measured (2 cores; before: the largest rectangle, after: the whole fan):

| frames | seed | fan covered % before / after | error % before / after | on the rectangle, after |
|---|---|---|---|---|
| 16 | 5 | 34.6 / 82.1 | 19.79 / 15.24 | 16.03 |
| 16 | 6 | 36.3 / 82.1 | 21.74 / 14.99 | 13.78 |
| 16 | 7 | 36.3 / 82.1 | 18.64 / 17.38 | 19.26 |
| 40 | 5 | 37.6 / 83.4 | 19.77 / 16.77 | 17.87 |
| 40 | 6 | 39.9 / 83.3 | 20.81 / 17.05 | 17.73 |
| 40 | 7 | 38.1 / 84.5 | 19.40 / 17.92 | 19.70 |

No pixel outside the fan is reported either way.  Time (seed 6, median of 5): 0.27 / 0.32 s for 16 frames,
0.38 / 0.63 s for 40.

Run: ``python benchmarks/elastogram_fan.py [--frames 16] [--seeds 5 6 7]``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from femreg.echo import find_fill  # noqa: E402
from femreg.elastogram import elastogram  # noqa: E402
from forward.display import bmode_uint8, sector_fan  # noqa: E402
from forward.freehand import FreehandMotion, simulate_freehand  # noqa: E402

MOTION = dict(press_hz=1.5, amplitude=0.02, pauses=((0.5, 0.7),), slide_mm_s=1.0, elevation_mm_s=1.0,
              gain_steps=((25, 2.5),))


def fan_loop(n_frames, seed):
    """(B-mode frames (n, n_axial, n_lateral) uint8 with the wedges 0, the fan (bool), the loop)."""
    loop = simulate_freehand(FreehandMotion(n_frames=max(n_frames, 40), **MOTION), seed=seed)
    bm = bmode_uint8(np.asarray(loop.frames[:n_frames], float), axis=1)
    n, m = bm.shape[1:]
    # an apex 8 mm above the first row, 74 % of the frame
    fan = sector_fan((n, m), loop.spacing, apex_mm=8.0, top_half_width_mm=0.2 * m * loop.spacing[1])
    bm[:, ~fan] = 0
    return bm, fan, loop


def on_frames(res, shape):
    """The elastogram on the full frames' grid (NaN where the run did not register)."""
    full = np.full(shape, np.nan)
    if res.region is None:
        full[:] = res.exx
    else:
        (a, b), (c, d) = res.region
        full[a:b, c:d] = res.exx
    return full


def normalised_error(loop, est, i, margin=0.1, where=None):
    """tests/test_elastogram.py's metric, percent; ``where`` (bool): on these pixels only."""
    pat = loop.strain_pattern(i, loop.pixel_points()).reshape(est.shape)
    ok = np.isfinite(est) if where is None else np.isfinite(est) & where
    m = int(margin * est.shape[0])
    ok[:m] = ok[-m:] = False
    return 100 * float(np.sqrt(np.mean((est[ok] / np.mean(est[ok]) - pat[ok] / np.mean(pat[ok])) ** 2)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 6, 7])
    args = ap.parse_args(argv)
    print("| seed | frames | usable pairs | fan covered % | outside fan px | error % | error on the rectangle % "
          "| wall s |")
    print("|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        bm, fan, loop = fan_loop(args.frames, seed)
        t = time.perf_counter()
        res = elastogram(bm, spacing=loop.spacing, origin=loop.origin)
        wall = time.perf_counter() - t
        full = on_frames(res, fan.shape)
        ok = np.isfinite(full)
        # the largest rectangle without fill (registered alone before the whole fan was): both compared there
        rect = find_fill(bm[0].astype(float), bm[-1].astype(float), loop.spacing, loop.origin)
        inner = np.zeros(fan.shape, bool)
        inner[slice(*rect.rows), slice(*rect.cols)] = True
        err, err_r = ((normalised_error(loop, full, res.ref_frame, where=w) if res.n_usable else float("nan"))
                      for w in (None, inner))
        print(f"| {seed} | {args.frames} | {res.n_usable} | {100 * np.mean(ok[fan]):.1f} | "
              f"{int(np.sum(ok & ~fan))} | {err:.2f} | {err_r:.2f} | {wall:.1f} |", flush=True)


if __name__ == "__main__":
    main()
