"""B-mode benchmark: the robustness benchmark's pairs (:mod:`benchmarks.robustness`, the single pairs) as a scanner's
display shows them -- envelope, log-compressed to ``--dynamic-range`` dB, 8 bits -- registered by femreg's defaults
and by the peers users would otherwise pick, same pairs, same error metric (:func:`benchmarks.robustness.errors`
over the same ROI), with femreg on the RF of the same pair as the reference.

The peers of :mod:`benchmarks.peers` take RF and form its envelope; here they are given the B-mode as their
envelope (``peers.envelope`` is the identity for the run): NCC block matching, SimpleITK B-spline, scikit-image
TV-L1.  Pairs without a usable result (FAILED for femreg) keep their error and are marked.

Run: ``python benchmarks/bmode.py [--cases WORDS] [--dynamic-range 50]``; prints one row per pair (total strain
error ``e``, %) and the count of pairs where femreg on B-mode beats every peer.
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
    sys.path.insert(0, str(ROOT))

from benchmarks import peers, robustness as rb  # noqa: E402


def to_bmode(rf, dynamic_range=50.0):
    """8-bit display B-mode of an RF frame: envelope (femreg.speckle.envelope), dB re its maximum, the top
    ``dynamic_range`` dB mapped to 0-255."""
    from femreg.speckle import envelope

    env = envelope(np.asarray(rf, float))
    db = 20.0 * np.log10(env / env.max() + 1e-12)
    return np.clip((db + dynamic_range) / dynamic_range * 255.0, 0, 255).astype(np.uint8)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="", help="words of case names to run (default: every single pair)")
    ap.add_argument("--dynamic-range", type=float, default=50.0)
    args = ap.parse_args(argv)
    import femreg

    cases = [c for c in rb.CASES if not c.sequence]
    if args.cases:
        cases = rb.select_cases(cases, args.cases)
    peers.envelope = lambda img: np.asarray(img, float)          # the B-mode is the peers' envelope
    names = ["femreg RF", "femreg B-mode"] + list(rb.PEER_METHODS)
    print(f"{'case':24s} " + " ".join(f"{n[:18]:>18s}" for n in names) + "   (total strain error e, %)")
    wins, n_cases, rows = 0, 0, []
    for case in cases:
        d = rb.make_data(case)
        sl = rb.roi_slices(d.ref.shape, d.spacing)
        t = rb.truth(d, None, sl)
        wl = 1.540 / d.probe.f0_mhz
        a, b = to_bmode(d.ref, args.dynamic_range), to_bmode(d.mov, args.dynamic_range)
        res, flags, secs = {}, {}, {}
        for name in names:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if name.startswith("femreg"):
                    A, B = (d.ref, d.mov) if name == "femreg RF" else (a, b)
                    r = femreg.register(A, B, spacing=d.spacing, origin=d.origin)
                    g = r.on_grid()
                    flags[name] = "" if r.success else " FAILED"
                else:
                    g = rb.PEER_METHODS[name](a.astype(float), b.astype(float), d.spacing, d.origin)
                    flags[name] = ""
            secs[name] = time.perf_counter() - t0
            res[name] = 100 * rb.errors(g, t, sl, wl)["e"]
        best_peer = min(res[n] for n in rb.PEER_METHODS)
        n_cases += 1
        win = res["femreg B-mode"] < best_peer and not flags["femreg B-mode"]
        wins += win
        rows.append((case.name, res, flags))
        print(f"{case.name:24s} " + " ".join(f"{res[n]:12.1f}{flags[n]:>6s}" for n in names)
              + ("" if win else "   <- a peer is better"), flush=True)
    print(f"\nfemreg on B-mode below every peer on {wins} of {n_cases} pairs; median e: "
          + ", ".join(f"{n} {np.median([r[1][n] for r in rows]):.1f} %" for n in names))
    return 0


if __name__ == "__main__":
    sys.exit(main())
