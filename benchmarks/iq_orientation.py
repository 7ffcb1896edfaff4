"""The swapped-spacing check of IQ data (:func:`femreg.orientation.check_remodulated`) on data it was not set on.

IQ frames are made from simulated RF (:func:`forward.pairs.make_pair`, every probe preset of
:data:`forward.pairs.PROBES`, SNR 10 and 30 dB, 10 x 8 and 30 x 30 mm, 2 % compression) and from the first frame of
the two in vivo sequences (``../shared/data/invivo_rf``, skipped if absent): analytic signal, shifted down by the
probe's centre frequency, decimated 1x, 2x and 4x along depth.  Each is remodulated with its spacing given in the
right order and exchanged; the table counts refusals.  A refusal of the right order is a false alarm; a pass of the
exchanged order a miss.

Second table: the sign-convention check (:func:`femreg.io.iq.iq_convention`) on pairs of moving tissue (every probe,
0.1 / 1 / 4 % compression, IQ decimated 1x and 3x; in vivo frames 1 -> 2 and 1 -> 4, decimated 1x and 4x), each with
the usual sign and conjugated: a verdict of the wrong sign is an error, "unknown" a miss; and each with its
frequency given 0.5, 0.8, 1.2 and 2 times too high: "frequency" is the verdict wanted.

Usage: ``python benchmarks/iq_orientation.py``.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from scipy.signal import hilbert, resample_poly  # noqa: E402

from femreg.io.frames import Frames  # noqa: E402
from femreg.io.iq import remodulate  # noqa: E402
from femreg.orientation import OrientationError, check_remodulated  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.pairs import PROBES, make_pair  # noqa: E402

C = 1540.0
INVIVO = Path(__file__).resolve().parents[2] / "shared" / "data" / "invivo_rf"


def iq_of(rf, dx, f_mhz, q):
    z = dx * np.arange(rf.shape[0])
    iq = hilbert(rf, axis=0) * np.exp(-2j * np.pi * f_mhz * 2e3 * z / C)[:, None]
    return resample_poly(iq, 1, q, axis=0)


def refused(iq, spacing, f_mhz) -> bool:
    rf, dz, _ = remodulate(iq, spacing[0], f_mhz)
    fr = Frames(frames=rf[None].astype(np.float32), spacing=(dz, spacing[1]),
                metadata={"iq": {"iq_spacing_mm": spacing[0]}})
    try:
        check_remodulated(fr)
    except OrientationError:
        return True
    return False


def main():
    cases = []
    for name, probe in PROBES.items():
        for snr in (10.0, 30.0):
            for size in ((10.0, 8.0), (30.0, 30.0)):
                p = make_pair(F.compression(0.02), probe=name, size_mm=size, snr_db=snr, seed=1)
                cases.append((f"{name} {snr:g} dB {size[0]:g}x{size[1]:g}", p.ref, p.spacing, probe.f0_mhz))
    for seq in ("seq299", "seq304"):
        f = INVIVO / seq / "frame1.raw"
        if f.exists():
            cases.append((f"in vivo {seq}", np.fromfile(f, "<f4").reshape(2000, 128), (0.02, 0.2), 4.158))
    false_alarms, misses, n = 0, [], 0
    print(f"{'case':28s} {'q':>2s} {'dx/dy':>6s}  right order  exchanged")
    for label, rf, (dx, dy), f in cases:
        for q in (1, 2, 4):
            iq = iq_of(rf, dx, f, q)
            a, b = refused(iq, (q * dx, dy), f), refused(iq, (dy, q * dx), f)
            n += 1
            false_alarms += a
            if not b:
                misses.append(f"{label} q={q} (dx/dy {q * dx / dy:.2f})")
            print(f"{label:28s} {q:2d} {q * dx / dy:6.2f}  {'REFUSED' if a else 'pass':11s}  "
                  f"{'refused' if b else 'MISSED'}")
    print(f"\n{n} cases: false alarms {false_alarms}, exchanged spacings refused {n - len(misses)} / {n}")
    for m in misses:
        print("  missed:", m)
    sign_table()


def sign_table():
    from femreg.io.iq import iq_convention

    pairs = []
    for name, probe in PROBES.items():
        for level in (0.001, 0.01, 0.04):
            p = make_pair(F.compression(level), probe=name, size_mm=(20.0, 15.0), snr_db=20.0, seed=2)
            for q in (1, 3):
                iq = [iq_of(x, p.spacing[0], probe.f0_mhz, q) for x in (p.ref, p.mov)]
                pairs.append((f"{name} {100 * level:g} % q={q}", iq, q * p.spacing[0], probe.f0_mhz))
    for seq in ("seq299", "seq304"):
        if (INVIVO / seq / "frame1.raw").exists():
            fr = [np.fromfile(INVIVO / seq / f"frame{k}.raw", "<f4").reshape(2000, 128) for k in (1, 2, 4)]
            for q in (1, 4):
                for k in (1, 2):
                    iq = [iq_of(x, 0.02, 4.158, q) for x in (fr[0], fr[k])]
                    pairs.append((f"in vivo {seq} 1->{(2, 4)[k - 1]} q={q}", iq, 0.02 * q, 4.158))
    wrong, unknown, worst = 0, 0, np.inf
    factors = (0.5, 0.8, 1.2, 2.0)
    caught, refused_right = {k: 0 for k in factors}, 0
    print(f"\n{'pair':30s} {'usual sign':>22s} {'conjugated':>22s}  frequency x{factors}: verdicts (best MHz)")
    for label, (a, b), dz, f in pairs:
        s, c = iq_convention(a, b, dz, f), iq_convention(np.conj(a), np.conj(b), dz, f)
        wrong += (s[0] != "standard" and s[0] != "unknown") + (c[0] != "conjugate" and c[0] != "unknown")
        refused_right += s[0] not in ("standard", "unknown")
        unknown += (s[0] == "unknown") + (c[0] == "unknown")
        worst = min(worst, s[1], 1 / c[1])
        off = [iq_convention(a, b, dz, f * k) for k in factors]
        for k, v in zip(factors, off):
            caught[k] += v[0] == "frequency"
        print(f"{label:30s} {s[0]:>10s} {s[1]:9.3g} {c[0]:>12s} {c[1]:9.3g}  "
              + " ".join(f"{v[0][:4]}({v[3]:.3g})" for v in off) + f"  [{s[2]} windows, best {s[3]:.3g} MHz]")
    print(f"{2 * len(pairs)} sign verdicts: wrong {wrong} (right frequency and sign refused: {refused_right}), "
          f"unknown {unknown}; the wrong sign explained the phases at least {worst:.3g} times worse")
    print("wrong frequency refused: " + ", ".join(f"x{k}: {caught[k]} / {len(pairs)}" for k in factors))


if __name__ == "__main__":
    main()
