"""``femreg.elastogram`` of a convex probe's loop: native (range, angle) frames (``geometry=femreg.Convex``, every
pair registered in physical x, y by femreg.geometry) against the same RF scan-converted onto a 0.1 mm Cartesian
grid with zero wedges around the fan (registered as a linear array's frames, the fan found by
femreg.echo.find_rf_fan).  A stiff r 4 mm disk (x4) at 20 mm depth in a compressed block (forward.fields.Inclusion,
plane strain), L7, R 40 mm, 64 rays 0.6 deg apart, 3-27 mm range, 0.8 % per frame, 30 dB.

Prints, per seed and loop: pairs usable, the share of the fan covered, the normalised strain error (RMS of the
estimated minus the true axial strain, each divided by its mean over the covered pixels less 10 % of the depth at
the top and bottom, percent; as benchmarks/elastogram_fan.py), the disk's strain ratio (mean normalised strain
within 0.6 r of its centre over that in the ring 1.5-2.5 r; the truth's beside it) and the wall time.  The truth is
taken at each pixel's frame-0 position (the pixel moved back by frame ``ref_frame``'s true displacement).

Run: ``python benchmarks/elastogram_convex.py [--seeds 1 2] [--frames 6]``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from femreg import Convex  # noqa: E402
from femreg.elastogram import elastogram  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.beam import make_beam_sequence  # noqa: E402

R_MM, PITCH_DEG, DISK = 40.0, 0.6, (20.0, 0.0, 4.0)


def loop(seed, n_frames, n_rays=64, depth_mm=24.0):
    field = F.Inclusion("stiff", "plane-strain", 0.01, radius_mm=DISK[2])
    return make_beam_sequence(field, Convex(radius_mm=R_MM, angle_pitch_deg=PITCH_DEG), probe="L7",
                              depth_mm=depth_mm, n_rays=n_rays, snr_db=30.0, seed=seed, n_frames=n_frames,
                              step=0.008)


def scan_converted(seq, dy=0.1):
    """The loop's RF on a Cartesian grid (range step axially, ``dy`` mm laterally), 0 outside the fan (int16
    counts, as a scanner's export)."""
    dr = seq.spacing[0]
    shape = seq.frames.shape[1:]
    X0, Y0 = seq.geometry.sample_positions(shape, seq.spacing, seq.origin)
    x, y = np.arange(X0.min(), X0.max(), dr), np.arange(Y0.min(), Y0.max(), dy)
    X, Y = np.meshgrid(x, y, indexing="ij")
    idx = seq.geometry.physical_to_index(np.column_stack([X.ravel(), Y.ravel()]), shape, (dr, 0), seq.origin)
    inside = (idx[0] >= 0) & (idx[0] <= shape[0] - 1) & (idx[1] >= 0) & (idx[1] <= shape[1] - 1)
    out = [np.round(np.where(inside, ndimage.map_coordinates(f, idx, order=3), 0.0).reshape(X.shape) * 1000)
           for f in seq.frames]
    return np.stack(out).astype(np.int16), (dr, dy), (float(x[0]), float(y[0]))


def score(res, seq):
    """(covered share of the fan, normalised strain error %, strain ratio, true strain ratio)."""
    e = np.asarray(res.exx, float)
    x = res.origin[0] + res.spacing[0] * np.arange(e.shape[0])
    y = res.origin[1] + res.spacing[1] * np.arange(e.shape[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])
    ok = np.isfinite(e).ravel()
    # the pixel's frame-0 position: moved back by frame ref_frame's true displacement (two fixed-point steps)
    p0 = pts.copy()
    for _ in range(2):
        u = seq.true_displacement(res.ref_frame, p0)
        p0 = pts - np.nan_to_num(u)
    t = seq.true_strain(1, p0)[:, 0]
    ok &= np.isfinite(t)
    lo, hi = np.percentile(X.ravel()[ok], [10.0, 90.0])
    m = ok & (X.ravel() >= lo) & (X.ravel() <= hi)
    en, tn = e.ravel() / np.mean(e.ravel()[m]), t / np.mean(t[m])
    err = 100.0 * float(np.sqrt(np.mean((en[m] - tn[m]) ** 2)))
    d = np.hypot(X.ravel() - DISK[0], Y.ravel() - DISK[1])
    disk, ring = ok & (d < 0.6 * DISK[2]), ok & (d > 1.5 * DISK[2]) & (d < 2.5 * DISK[2])
    ratio = float(np.mean(en[disk]) / np.mean(en[ring])) if disk.any() and ring.any() else float("nan")
    true = float(np.mean(tn[disk]) / np.mean(tn[ring])) if disk.any() and ring.any() else float("nan")
    fan = res.data_mask if res.data_mask is not None else np.ones(e.shape, bool)
    return float(np.isfinite(e)[fan].mean()), err, ratio, true


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--frames", type=int, default=6)
    a = ap.parse_args(argv)
    print("| seed | loop | usable | fan covered % | error % | strain ratio (true) | s |")
    print("|---|---|---|---|---|---|---|")
    for seed in a.seeds:
        seq = loop(seed, a.frames)
        runs = (("native", dict(frames=seq.frames, spacing=seq.spacing[0], origin=seq.origin, geometry=seq.geometry)),
                ("scan-converted", dict(zip(("frames", "spacing", "origin"), scan_converted(seq)))))
        for name, kw in runs:
            t = time.perf_counter()
            res = elastogram(**kw)
            wall = time.perf_counter() - t
            cov, err, ratio, true = score(res, seq)
            print(f"| {seed} | {name} | {res.n_usable}/{len(res.pairs)} | {100 * cov:.1f} | {err:.2f} | "
                  f"{ratio:.3f} ({true:.3f}) | {wall:.1f} |", flush=True)


if __name__ == "__main__":
    main()
