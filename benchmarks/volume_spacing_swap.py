"""Can a volume's lateral and elevational spacings, typed exchanged (``--spacing DX DZ DY`` for a probe whose line
pitch DY differs from its plane spacing DZ), be recognised from the RF before registering?

The carrier witnesses the axial spacing only (:mod:`femreg.orientation`).  Across the beam the data hold the
speckle: its cell (FWHM of the envelope autocorrelation) along y and along z, in samples, is the beam width over the
pitch along that axis; the spacing given turns it into mm.  Exchanging DY and DZ leaves the samples as they are and
multiplies the elevational over lateral cell aspect ``A = cell_z / cell_y`` (mm) by ``(DY / DZ)^2``, the lateral
cell by ``DZ / DY`` and the elevational one by ``DY / DZ``.  A rule can only tell the two readings apart where the
aspect (or the cells against the wavelength, c / f read from the carrier) of right volumes does not reach the
values exchanged ones take.  The frames' counterpart works (:data:`femreg.orientation.MIN_LATERAL_CELL_PERIODS`):
there the factor is ``(dx / dy)^2``, 0.01 for a 0.02 mm axial sample against a 0.2 mm line pitch.

For each probe (:data:`forward.volume.VOLUME_PROBES` and five more: a 7.5 MHz and a 5 MHz wobbler, a sweep finer
than the line pitch, a square-aperture and a wide-aperture matrix array), seeds 0 and 1, one volume (SNR 30 dB,
4-20 mm deep, 8 lateral and 6 elevational beam widths plus 4 mm across): the cells along y and z (samples,
interpolated FWHM, the depth's mean level removed), in mm with the right spacing, the aspect right and exchanged,
in the upper and lower half of the depth; then every right / exchanged pair of probes whose aspects lie within 10 %
(no rule on the aspect separates them with that margin) and each exchanged reading's cells against the range of
the right ones in wavelengths.

Measured (2026-12-08): the cells read the beam widths (0.91-1.07 x the FWHM at focus; the two seeds within 3 %,
the two halves of the depth within 7 %).  Right aspects 0.71-3.16 (the probes' beam aspects, 0.7-3.1), exchanged
0.32-8.06.  Exchanged readings inside the right range: matrix7 (DY 0.2, DZ 0.25 mm) 1.41-1.42, wobbler5 (0.3,
0.4) 1.41-1.43, swept3 (0.4, 0.5) 0.96-0.98 -- the last 3-6 % from the right square-aperture matrix array's
1.01-1.02, the first two 6-9 % from right swept3's 1.51-1.54: no rule on the aspect separates them with a 10 %
margin.  In wavelengths (c / f, f from the carrier) the right cells span lateral 2.86-4.75, elevational 2.91-11.32;
matrix7's and wobbler5's exchanged readings are lateral 4.84 and 4.79 (0.8-1.9 % above the right ones here), their
elevational cells inside, and the frames' probes and the in vivo frames of :mod:`femreg.orientation` read lateral
cells of 4.8-13 RF periods, 2.4-6.5 wavelengths: a right lateral cell of 4.8-5.9 wavelengths is ordinary.  A note
below a fixed aspect would catch the exchanges of five probes (A < 0.6: matrix12, matrix4sq, matrixwide, paper3d,
wobbler7) and note no right volume, with 0-18 % between them (matrix12 exchanged 0.60, matrixwide right 0.71), and
a probe whose elevational beam is half its lateral one (the 7 MHz matrix array of benchmarks/psf3d_crosscheck.py
8 mm above its elevational focus in pymust's SIMUS3: elevational 0.87, lateral 1.75 mm) would read as exchanged.
So nothing is refused or noted before registering: an exchanged volume of matrix7, swept3 or wobbler5 (pitch ratios
1.25-1.33) looks like another plausible probe, and whether an exchange shows depends on the beams as much as on the
pitches (at the same ratio 1.33 the square-aperture matrix array's exchanged aspect reads 0.57, wobbler5's 1.41).
The failed registration's hint of ``femreg register`` (:func:`femreg.cli._volume._exchanged_hint`) stays the place
that names the mistake.

Run: ``python benchmarks/volume_spacing_swap.py`` (one thread, about 2.5 min on the shared machine).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

from femreg.speckle import envelope  # noqa: E402
from forward.volume import VOLUME_PROBES, VolumeProbe, make_volume_sequence  # noqa: E402

#: The presets and five more probes (f0 MHz, fs MHz, lateral pitch, elevational pitch, lateral / elevational beam
#: FWHM mm, cycles, lateral focus, elevational focus mm).
PROBES = dict(VOLUME_PROBES, **{
    "wobbler7": VolumeProbe(7.5, 40.0, 0.2, 0.6, 0.8, 2.5, 2.365, None, 20.0, name="wobbler7"),
    "wobbler5": VolumeProbe(5.0, 30.0, 0.3, 0.4, 1.2, 3.0, 2.365, None, 30.0, name="wobbler5"),
    "finesweep": VolumeProbe(7.0, 30.8, 0.3, 0.15, 1.0, 2.0, 2.365, None, 20.0, name="finesweep"),
    "matrix4sq": VolumeProbe(4.0, 20.0, 0.3, 0.4, 1.2, 1.2, 2.365, None, None, name="matrix4sq"),
    "matrixwide": VolumeProbe(5.0, 30.0, 0.2, 0.3, 1.4, 1.0, 2.365, None, None, name="matrixwide"),
})
SEEDS = (0, 1)
TOP, DEPTH = 4.0, 16.0
MARGIN = 1.10                        # aspects within 10 % of each other: no rule separates them with that margin


def cell_samples(e, axis: int) -> float:
    """FWHM (samples, linear interpolation at the half maximum) of the envelope autocorrelation of ``e`` along
    ``axis``, summed over the other axes (zero-padded FFT: linear correlation)."""
    ea = np.moveaxis(e, axis, -1)
    m = ea.shape[-1]
    F = np.fft.rfft(ea, n=2 * m, axis=-1)
    ac = np.fft.irfft(np.mean((F.real ** 2 + F.imag ** 2).reshape(-1, F.shape[-1]), axis=0), n=2 * m)[:m]
    ac = ac / ac[0]
    k = int(np.flatnonzero(ac < 0.5)[0])
    return 2.0 * (k - 1 + (ac[k - 1] - 0.5) / (ac[k - 1] - ac[k]))


def measure(name: str, pr: VolumeProbe, seed: int) -> dict:
    """Cells (samples) along y and z over the whole depth and its two halves; the probe's spacing and wavelength."""
    size = (DEPTH, 8 * pr.beam_fwhm_mm + 4.0, 6 * pr.elevation_fwhm_mm + 4.0)
    v = make_volume_sequence([], pr, size, seed=seed, top_mm=TOP).frames[0]
    env = envelope(v.reshape(v.shape[0], -1)).reshape(v.shape)
    e = env - env.mean(axis=(1, 2), keepdims=True)       # a level changing with depth only is no speckle
    half = e.shape[0] // 2
    parts = {"all": e, "upper": e[:half], "lower": e[half:]}
    return dict(name=name, seed=seed, spacing=pr.spacing, beams=(pr.beam_fwhm_mm, pr.elevation_fwhm_mm),
                wavelength=pr.c_m_s / pr.f0_mhz / 1e3, shape=v.shape,
                cells={k: (cell_samples(p, 1), cell_samples(p, 2)) for k, p in parts.items()})


def readings(r: dict, part: str = "all") -> dict:
    """Cells in mm and the aspect with the spacing right and exchanged."""
    _, dy, dz = r["spacing"]
    cy, cz = r["cells"][part]
    return {"right": (cy * dy, cz * dz), "exchanged": (cy * dz, cz * dy)}


def main() -> None:
    t0 = time.perf_counter()
    rows = []
    print(f"{'probe':10s} seed  DY   DZ   beams mm    cells (samples)  cells mm (/beam)      aspect right / "
          "exchanged (upper, lower half)")
    for name, pr in PROBES.items():
        for seed in SEEDS:
            r = measure(name, pr, seed)
            rows.append(r)
            rd = readings(r)
            (ly, lz), (xy, xz) = rd["right"], rd["exchanged"]
            by, bz = r["beams"]
            halves = " ".join(f"{readings(r, p)['right'][1] / readings(r, p)['right'][0]:.2f}/"
                              f"{readings(r, p)['exchanged'][1] / readings(r, p)['exchanged'][0]:.2f}"
                              for p in ("upper", "lower"))
            cy, cz = r["cells"]["all"]
            print(f"{name:10s} {seed:4d}  {r['spacing'][1]:.2f} {r['spacing'][2]:.2f} {by:.1f}/{bz:.1f}  "
                  f"{cy:6.2f} {cz:6.2f}    {ly:.3f} ({ly / by:.2f}) {lz:.3f} ({lz / bz:.2f})  "
                  f"{lz / ly:5.2f} / {xz / xy:5.2f}  ({halves})", flush=True)

    def aspect(r, which):
        a, b = readings(r)[which]
        return b / a

    right = [(r["name"], aspect(r, "right")) for r in rows]
    exch = [(r["name"], aspect(r, "exchanged")) for r in rows]
    lo, hi = min(a for _, a in right), max(a for _, a in right)
    print(f"\nright aspects {lo:.2f}-{hi:.2f}; exchanged {min(a for _, a in exch):.2f}-{max(a for _, a in exch):.2f}")
    inside = sorted({n for n, a in exch if lo <= a <= hi})
    print(f"exchanged readings inside the right range: {', '.join(inside) or 'none'}")
    close = sorted({(n, m, round(a, 2), round(b, 2)) for n, a in exch for m, b in right
                    if max(a, b) / min(a, b) < MARGIN and n != m})
    print(f"exchanged / right pairs within {100 * (MARGIN - 1):.0f} % of each other (no aspect rule separates them "
          "with that margin):")
    for n, m, a, b in close:
        print(f"  {n} exchanged {a:.2f} ~ {m} right {b:.2f}")

    def in_wavelengths(r, which):
        a, b = readings(r)[which]
        return a / r["wavelength"], b / r["wavelength"]

    R = np.array([in_wavelengths(r, "right") for r in rows])
    print(f"\ncells in wavelengths, right: lateral {R[:, 0].min():.2f}-{R[:, 0].max():.2f}, elevational "
          f"{R[:, 1].min():.2f}-{R[:, 1].max():.2f}")
    for r in rows[::len(SEEDS)]:
        wy, wz = in_wavelengths(r, "exchanged")
        where = ["inside" if R[:, k].min() <= w <= R[:, k].max() else "outside" for k, w in enumerate((wy, wz))]
        print(f"  {r['name']:10s} exchanged: lateral {wy:5.2f} ({where[0]}), elevational {wz:5.2f} ({where[1]})")
    for t in (0.6, 0.8, 1.0):
        caught = sorted({n for n, a in exch if a < t})
        false = sorted({n for n, a in right if a < t})
        print(f"note below aspect {t}: exchanged caught on {len(caught)} of {len(PROBES)} probes "
              f"({', '.join(caught)}); right volumes noted: {', '.join(false) or 'none'}")
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
