"""Volume tracking's retry of a flagged increment (``femreg.track`` on volumes, accumulate mode): simulated 7 MHz RF
volumes, 6 x 6 x 6 mm (300 x 30 x 24 voxels, tests/_volumes.py), under uniaxial compression.

* ``reversal``: frame compressions 0, 2.5, 5, 2.5, 3 % -- frame 3 releases half the compression, so frame 2's
  increment (+2.5 %) is a start 5 % off (150 um, 1.4 RF periods, at the top and bottom) for frame 3's -2.5 %.
* ``jump``: 0, 0.5, 1, 6, 6.5 % -- frame 3 jumps 5 %: frame 2's increment is a start 4.5 % off (135 um), zero
  motion 5 % (150 um); only the pair's own coarse-to-fine search finds it.
* ``steady``: 0, 0.5, 1, 1.5, 2 % -- every increment alike; nothing is flagged, nothing retried (the results
  must be those of the code without a retry: ``--save`` / ``--compare``).

Prints per frame: flag, whether it was retried, the NCC after, and the axial displacement error of frame 0 -> k
(RMS over the mesh nodes, um), and the wall and CPU time of each track.

    python benchmarks/volume_track_retry.py                        # seeds 0 1 2, both loops
    python benchmarks/volume_track_retry.py --code /path/to/other  # another checkout's femreg (before / after)
    python benchmarks/volume_track_retry.py --save a.npz / --compare a.npz   # nodal u equality between codes

Measured 2026-12-07 (seeds 0-2; frame 0 -> 3 / 4 axial u RMS error), before the retry -> with it: reversal
106-118 / 105-190 um, volumes 3 and 4 flagged -> volume 3 retried, none flagged, 0.07-0.13 / 0.09-0.15 um; jump
103-116 / 103-115 um, flagged -> retried, none flagged, 0.16-0.31 / 0.18-0.34 um (the retry from zero motion
relative to S instead: frame 3 still flagged, NCC after 0.09-0.15); steady: nodal u equal (max difference 0).
CPU per loop, shared 2-core machine at load ~4: reversal 1.3-1.9 -> 1.4-2.3 s, jump 1.0-1.3 -> 1.6-2.4 s.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LOOPS = {"reversal": (0.0, 0.025, 0.05, 0.025, 0.03), "jump": (0.0, 0.005, 0.01, 0.06, 0.065),
         "steady": (0.0, 0.005, 0.01, 0.015, 0.02)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--loops", nargs="+", default=list(LOOPS), choices=list(LOOPS))
    ap.add_argument("--code", help="a checkout whose femreg is run (default: this one)")
    ap.add_argument("--save", help="write every frame's nodal u to this .npz")
    ap.add_argument("--compare", help="print max |u - u_saved| per frame against a --save file")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "tests"))
    sys.path.insert(0, str(Path(a.code).resolve() if a.code else ROOT))
    import femreg
    from _volumes import compression_sequence

    print(f"femreg from {Path(femreg.__file__).parent}")
    saved, ref = {}, np.load(a.compare) if a.compare else None
    for name in a.loops:
        for seed in a.seeds:
            frames, spacing, field = compression_sequence(LOOPS[name], seed=seed)
            t0, c0 = time.perf_counter(), time.process_time()
            tr = femreg.track(frames, spacing=spacing, element_size=2.0)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            retried = list(getattr(tr, "retried", []))
            print(f"{name} seed {seed}: {len(tr)} increments in {wall:.2f} s ({cpu:.2f} s CPU), "
                  f"{sum(bool(f) for f in tr.flags)} flagged, retried {retried}")
            for k, (res, flag) in enumerate(zip(tr.accumulated, tr.flags), start=1):
                pts = res.mesh.p.T
                err = 1e3 * np.sqrt(np.mean((res.displacement(pts)[:, 0] - field(k, pts)[:, 0]) ** 2))
                key = f"{name}_{seed}_{k}"
                saved[key] = np.asarray(res.u, float)
                diff = ""
                if ref is not None and key in ref.files:
                    diff = f"  max |u - saved| {np.max(np.abs(saved[key] - ref[key])):.3g} mm"
                print(f"  frame {k}: ncc {res.ncc_after:.3f}, axial u error {err:8.2f} um"
                      f"{'  RETRIED' if k in retried else ''}{'  FLAGGED: ' + flag[:90] if flag else ''}{diff}")
    if a.save:
        np.savez(a.save, **saved)


if __name__ == "__main__":
    main()
