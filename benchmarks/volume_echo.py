"""Where the echo is in a volume (femreg.echo_volume): RF volumes recorded to full depth, the echo sinking to the
receiver's noise floor at 40 / 60 / 80 % of the depth (round-trip attenuation without time-gain compensation,
forward.volume ``echo_gain_db`` = forward.pairs.attenuation_gain_db, SNR 30 dB at the face: the 2D benchmark's
parameters), 20 x 15 x 10 mm from 2 mm down, an affine field (1 % compression, half of it as lateral and
elevational expansion, 0.5 % shear e_xy, 0.3 degree rotation about z).

For each probe and floor depth D: the detected depth against D (where the echo power equals the noise power), and
the six-component total strain error (shear counted twice) over the echo -- voxel centres from 2 mm below the top
to 2 mm above D, 2 mm inside the lateral and elevational faces -- of the volume registered whole (``roi=None``),
with the detected box (``roi="auto"``, the default) and cropped by hand (``depth=(top, D)``).  CPU time of each
registration (``time.process_time``, one thread) and the process's peak memory.

    python benchmarks/volume_echo.py                                   # matrix7, swept3, matrix12 x 40/60/80 %
    python benchmarks/volume_echo.py --probes matrix7 --fracs 0.6      # one case
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SNR, TOP, SIZE = 30.0, 2.0, (20.0, 15.0, 10.0)
WEIGHTS = np.array([1, 1, 1, 2, 2, 2.0])


def floor_volume(probe, frac, seed=0):
    from forward.pairs import alpha_for_floor, attenuation_gain_db
    from forward.volume import VOLUME_PROBES, Affine3D, make_volume_pair

    f0 = VOLUME_PROBES[probe].f0_mhz
    depth = TOP + frac * SIZE[0]
    gain = attenuation_gain_db(alpha_for_floor(depth, SNR, f0), f0)
    field = Affine3D(0.01, shear={"xy": 0.005}, rotation_deg=(0.0, 0.0, 0.3))
    pair = make_volume_pair(field, probe, SIZE, seed=seed, top_mm=TOP, snr_db=SNR, echo_gain_db=gain)
    return pair, depth


def strain_error(res, pair, depth, margin=2.0) -> float:
    """Total strain error (%) over the echo (module docstring) where the result has a mesh, and the fraction of
    the echo's voxels it covers."""
    g = pair.grid
    ax = [g.axis(a) for a in range(3)]
    ext = g.extent()
    keep = [(ax[0] >= ext[0] + margin) & (ax[0] <= depth - margin),
            (ax[1] >= ext[2] + margin) & (ax[1] <= ext[3] - margin),
            (ax[2] >= ext[4] + margin) & (ax[2] <= ext[5] - margin)]
    X = np.meshgrid(ax[0][keep[0]][::2], ax[1][keep[1]], ax[2][keep[2]], indexing="ij")
    P = np.column_stack([x.ravel() for x in X])
    est, true = res.strain(P), pair.true_strain(1, P)
    ok = np.all(np.isfinite(est), axis=1)          # a box detected too shallow leaves the deepest echo out
    err = np.sqrt(np.sum(WEIGHTS * (est[ok] - true[ok]) ** 2) / np.sum(WEIGHTS * true[ok] ** 2)) if ok.any() else np.nan
    return float(100.0 * err), float(np.mean(ok))


def main(argv=None):
    import femreg
    from femreg.echo_volume import find_echo_volume

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--probes", nargs="+", default=["matrix7", "swept3", "matrix12"])
    ap.add_argument("--fracs", nargs="+", type=float, default=[0.4, 0.6, 0.8])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write the rows as JSON")
    args = ap.parse_args(argv)
    rows = []
    print("| probe | voxels | floor D mm | detected mm | error mm | strain error whole / auto / hand % | CPU s "
          "whole / auto / hand | detection s |")
    print("|---|---|---|---|---|---|---|---|")
    for probe in args.probes:
        for frac in args.fracs:
            pair, depth = floor_volume(probe, frac, args.seed)
            kw = dict(spacing=pair.spacing, origin=pair.origin)
            t = time.process_time()
            box = find_echo_volume(pair.ref, pair.mov, **kw)
            t_det = time.process_time() - t
            detected = box.roi_mm[1]
            row = dict(probe=probe, shape=list(pair.ref.shape), floor_mm=depth, detected_mm=detected,
                       depth_error_mm=detected - depth, detection_s=t_det, excluded=box.excluded, box=box.roi_mm)
            top = float(pair.grid.extent()[0])
            for name, opt in (("whole", dict(roi=None)), ("auto", {}), ("hand", dict(depth=(top, depth)))):
                t = time.process_time()
                res = femreg.register(pair.ref, pair.mov, **kw, **opt)
                row[f"cpu_{name}_s"] = time.process_time() - t
                row[f"strain_error_{name}_pct"], row[f"covered_{name}"] = strain_error(res, pair, depth)
                row[f"success_{name}"] = bool(res.success)
                row[f"roi_{name}"] = res.roi
            rows.append(row)
            print(f"| {probe} | {' x '.join(map(str, pair.ref.shape))} | {depth:.1f} | {detected:.2f} | "
                  f"{detected - depth:+.2f} | {row['strain_error_whole_pct']:.2f} / {row['strain_error_auto_pct']:.2f}"
                  f" / {row['strain_error_hand_pct']:.2f}" + ("" if row["covered_auto"] == 1 else
                  f" ({row['covered_auto']:.0%} of the echo in the auto box)") + f" | {row['cpu_whole_s']:.1f} / {row['cpu_auto_s']:.1f} / "
                  f"{row['cpu_hand_s']:.1f} | {t_det:.2f} |", flush=True)
    print(f"peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f} GB")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
