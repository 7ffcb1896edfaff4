"""Test set of the orientation and sampling check (:mod:`femreg.orientation`): every pair as given, transposed
(frames lines x samples, spacing exchanged with them) and with the two spacings swapped, plus the envelope of the
reference (no carrier: must pass).  Pairs: simulated probes 3-15 MHz (:data:`forward.pairs.PROBES`, several
sizes, noise levels and seeds), the robustness benchmark's pairs (:mod:`benchmarks.robustness`), the in vivo
sequences (consecutive pairs, when ../shared/data/invivo_rf is there) and the paper's sequences that are cached
(:func:`forward.sequences.get_sequence`, frames 0 -> 6; ``--paper`` simulates the missing ones).

The check runs on the reference frame as :func:`femreg.register` does.  Prints one line per pair and the totals:
detections (transposed and swapped refused), false alarms (a correct pair or an envelope refused).

Run: ``python benchmarks/orientation_check.py [--paper] [--no-robustness]`` (about 2 min with the paper sequences
cached).  Measured: 49 pairs, 98 of 98 transposed/swapped refused, 0 of 98 correct frames and envelopes refused.
The envelope and log B-mode of each reference (no carrier) are checked with their spacings exchanged, in metres and
in centimetres: on 45 pairs 0 of 45 B-modes refused, exchanged 90 of 90, metres 90 of 90, centimetres 13 of 90
(the cells of 3-7 MHz probes 10 x smaller still look like a finer probe's).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from femreg.orientation import diagnose  # noqa: E402
from femreg.pyramid import envelope  # noqa: E402

INVIVO = ROOT.parent / "shared" / "data" / "invivo_rf"


def simulated_pairs():
    from forward import fields as F
    from forward.pairs import PROBES, make_pair

    for name, probe in PROBES.items():
        for size, snr, seed in (((30, 20), 30, 0), ((15, 10), 10, 1), ((50, 40), 20, 2)):
            p = make_pair(F.compression(0.02), probe, size, snr, seed=seed)
            yield f"sim {name} {size[0]}x{size[1]}mm {snr}dB s{seed}", p.ref, p.mov, p.spacing


def robustness_pairs():
    from benchmarks.robustness import CASES, make_data

    for case in CASES:
        d = make_data(case)
        if case.sequence:
            yield f"robustness {case.name}", d.frames[0], d.frames[-1], d.spacing
        else:
            yield f"robustness {case.name}", d.ref, d.mov, d.spacing


def invivo_pairs():
    for seq in ("seq299", "seq304"):
        folder = INVIVO / seq
        if not folder.is_dir():
            continue
        frames = [np.fromfile(folder / f"frame{k}.raw", "<f4").reshape(2000, 128) for k in range(1, 7)]
        for k in range(5):
            yield f"in vivo {seq} {k + 1}->{k + 2}", frames[k], frames[k + 1], (0.02, 0.2)


def paper_pairs(simulate: bool):
    from forward.sequences import PAPER_DATASETS, get_sequence, sequence_cache_dir

    for model, inc in PAPER_DATASETS:
        name = f"{model}-{inc}"
        if not simulate and not any(sequence_cache_dir(None).glob(f"{name}_seed0_*.npz")):
            continue
        s = get_sequence(model, inc, seed=0)
        yield f"paper {name} 0->6", s.frames[0], s.frames[6], tuple(s.spacing)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paper", action="store_true", help="simulate paper sequences missing from the cache")
    ap.add_argument("--no-robustness", action="store_true")
    args = ap.parse_args(argv)
    sources = [simulated_pairs(), invivo_pairs(), paper_pairs(args.paper)]
    if not args.no_robustness:
        sources.insert(1, robustness_pairs())
    n = detected = false_alarm = bmode_alarm = 0
    env_found = [0, 0, 0]
    for src in sources:
        for name, ref, mov, sp in src:
            sp = tuple(float(s) for s in sp)
            ok = diagnose(ref, sp)
            e = envelope(ref)
            bm = 20.0 * np.log10(e / e.max() + 1e-6)            # log-compressed B-mode
            env = diagnose(e, sp)
            bmode = diagnose(bm, sp)
            tr = diagnose(np.ascontiguousarray(ref.T), sp[::-1])
            sw = diagnose(ref, sp[::-1])
            # envelope / B-mode mistakes: exchanged spacings, metres and centimetres typed as mm
            env_sw = [diagnose(x, sp[::-1]).problem for x in (e, bm)]
            env_m = [diagnose(x, tuple(v / 1e3 for v in sp)).problem for x in (e, bm)]
            env_cm = [diagnose(x, tuple(v / 10.0 for v in sp)).problem for x in (e, bm)]
            n += 1
            detected += bool(tr.problem) + bool(sw.problem)
            false_alarm += bool(ok.problem) + bool(env.problem)
            bmode_alarm += bool(bmode.problem)
            env_found[0] += sum(bool(p) for p in env_sw)
            env_found[1] += sum(bool(p) for p in env_m)
            env_found[2] += sum(bool(p) for p in env_cm)
            print(f"{name:42s} ok:{ok.problem or 'pass':10s} env:{env.problem or 'pass':10s} "
                  f"B-mode:{bmode.problem or 'pass':8s} cells {env.axial_cell_mm:.3g} x {env.lateral_cell_mm:.3g} "
                  f"mm, env/B-mode swapped {env_sw}, m {env_m}, cm {env_cm}; "
                  f"T:{tr.problem or 'MISSED':10s} swap:{sw.problem or 'MISSED':10s} "
                  f"f={ok.frequency_mhz:5.2f} MHz, lateral cell {ok.cell_periods:5.2f} periods "
                  f"(swapped {sw.cell_periods:4.2f}), carrier ratio {ok.carrier[0]:.3f}/{ok.carrier[1]:.2f}",
                  flush=True)
    print(f"\n{n} pairs: {detected} of {2 * n} transposed/swapped refused, {false_alarm} false alarms on "
          f"{2 * n} correct frames and envelopes, {bmode_alarm} on {n} log B-modes; envelopes and B-modes: "
          f"exchanged spacings refused on {env_found[0]}, metres on {env_found[1]}, centimetres on {env_found[2]} "
          f"of {2 * n}")
    return 0 if detected == 2 * n and false_alarm == 0 and bmode_alarm == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
