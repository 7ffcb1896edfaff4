"""Test set of the axial-spacing checks (:func:`femreg.orientation.check_sampling`, :func:`frequency_note`).

For the simulated probes (:data:`forward.pairs.PROBES` plus a 5 MHz probe sampled at 20 MHz and a 10 MHz one at 30
MHz; sizes 15 x 10 to 50 x 40 mm, SNR 10-30 dB) and the in vivo frames (when ../shared/data/invivo_rf is there):

* the RF carrier (:func:`carrier_frequency`, cycles per mm axially and MHz) at the correct spacing, and its ratio
  to the probe's centre (transmit) frequency;
* every reference written as an Ultrasonix ``.rf`` file (``sf`` = the probe's sampling rate, ``txf`` its centre
  frequency) and read with the axial spacing as given and scaled by 0.5, 2, 2.7, 1/2.7, 10 and 0.1: refused,
  noted or passed (no header: the frequency note register adds);
* the same file with a wrong sampling rate in its header (x 0.5, x 2) and the spacing taken from it: the
  transmit check alone.

Run: ``python benchmarks/spacing_check.py`` (about 1 min).  Measured: carrier / centre frequency 0.977-1.077 on the
21 simulated references (7 probes x 3 sizes); in vivo 4.52-4.56 MHz (5.87-5.92 cycles/mm) at 0.02 mm.  Every
correct spacing passed without a note (21 of 21); typed 0.5 / 2 / 2.7 / 1/2.7 / 10 / 0.1 x against the header's sf:
refused 21 of 21 each.  The header's sf halved or doubled, the spacing taken from it (2 x, 0.5 x): noted 21 of 21
each (carrier / transmit 0.49-0.54, 1.95-2.15), not refused: harmonic imaging reads 2.  Without any header only the
carrier's band is a witness (``frequency_note``): 2.7 x too large noted on the 3 and 5 MHz probes (6 of 21) and the
in vivo frames (12 of 12), 1/2.7 x on the 7.5-15 MHz probes (12 of 21); the 5.5 MHz paper probe reads 2.0 and 14.9
MHz, inside the band, and the in vivo frames at 1/2.7 x 12.3 MHz: not noted.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from femreg.io import read_frames  # noqa: E402
from femreg.io.ultrasonix import write_ultrasonix  # noqa: E402
from femreg.orientation import OrientationError, carrier_frequency, frequency_note  # noqa: E402

INVIVO = ROOT.parent / "shared" / "data" / "invivo_rf"
FACTORS = (0.5, 2.0, 2.7, 1 / 2.7, 10.0, 0.1)


def probes():
    from forward.pairs import PROBES, Probe

    out = dict(PROBES)
    out["L5/20"] = Probe(5.0, 20.0, 0.3, 1.2, name="L5/20")
    out["L10/30"] = Probe(10.0, 30.0, 0.15, 0.6, name="L10/30")
    return out


def verdict(path, spacing):
    try:
        fr = read_frames(path, spacing=spacing)
    except OrientationError as exc:
        return "refused" if exc.problem == "sampling" else f"refused ({exc.problem})"
    return "noted" if fr.metadata.get("sampling_notes") else "passed"


def main():
    from forward import fields as F
    from forward.pairs import make_pair

    tally, ratios = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for name, probe in probes().items():
            for size, snr, seed in (((30, 20), 30, 0), ((15, 10), 10, 1), ((50, 40), 20, 2)):
                p = make_pair(F.compression(0.02), probe, size, snr, seed=seed)
                dx, dy = p.spacing
                f = carrier_frequency(p.ref, dx)
                ratios.append(f / probe.f0_mhz)
                frames = np.stack([p.ref, p.mov])
                frames = frames / np.abs(frames).max() * 20000
                path = Path(tmp) / "a.rf"
                write_ultrasonix(path, frames, (dx, dy), header={"txf": int(probe.f0_mhz * 1e6)})
                row = {"correct": verdict(path, (dx, dy))}
                for k in FACTORS:
                    row[f"x{k:.3g}"] = verdict(path, (dx * k, dy))
                notes = {f"x{k:.3g}": bool(frequency_note(carrier_frequency(p.ref, dx * k))) for k in (2.7, 1 / 2.7)}
                for k in (0.5, 2.0):        # the header's rate wrong, the spacing taken from it
                    bad = Path(tmp) / "b.rf"
                    write_ultrasonix(bad, frames, sampling_frequency=probe.fs_mhz * 1e6 * k,
                                     header={"txf": int(probe.f0_mhz * 1e6)})
                    row[f"sf x{k:g}"] = verdict(bad, (None, dy))
                for key, v in row.items():
                    tally.setdefault(key, {}).setdefault(v, 0)
                    tally[key][v] += 1
                print(f"{name:7s} {size} {snr:2d} dB: f {f:6.2f} MHz ({2 * f / 1.54:6.2f} cycles/mm), "
                      f"/ f0 {f / probe.f0_mhz:.3f}; {row}; note without header {notes}", flush=True)
    print(f"carrier / centre frequency: {min(ratios):.3f}-{max(ratios):.3f}")
    for seq in ("seq299", "seq304"):
        folder = INVIVO / seq
        if not folder.is_dir():
            continue
        for k in range(1, 7):
            a = np.fromfile(folder / f"frame{k}.raw", "<f4").reshape(2000, 128)
            f = carrier_frequency(a, 0.02)
            print(f"{seq} frame{k}: {f:.2f} MHz ({2 * f / 1.54:.2f} cycles/mm) at 0.02 mm; note at 2.7 x: "
                  f"{bool(frequency_note(f / 2.7))}, at 1/2.7 x: {bool(frequency_note(f * 2.7))}")
    for key, v in tally.items():
        print(f"{key:10s} {v}")


if __name__ == "__main__":
    main()
