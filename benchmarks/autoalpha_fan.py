"""``alpha="auto"`` on scan-converted fan B-mode pairs: the alpha chosen and the axial strain error inside the fan,
for ``femreg.register`` and ``femreg.track`` (two frames), plus the same pair without fill (the whole B-mode frames)
and as RF, where nothing is masked.

Each case: a forward.pairs pair (probe, field, seed) as 8-bit B-mode (50 dB) inside a sector's fan with black
wedges (tests/test_bmode.py's ``_fan``).  Error: RMS of estimated minus true axial strain over the pixels with a
finite estimate inside the fan, divided by the mean true strain magnitude there (tests/test_bmode.py's metric).

Measured (2 cores; before: ``track`` registered the candidates without the fan's weights and ``choose_alpha`` read
the image term and the strain change over the fill too; after: the fan's mask throughout): docs/autoalpha.md
("Fan frames").

Run: ``python benchmarks/autoalpha_fan.py [--cases 0 1 2 3] [--no-plain]``; prints one markdown row per case and
call.  Runs on any checkout (``PYTHONPATH`` picks the one measured).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))

import femreg  # noqa: E402
from forward import fields as F  # noqa: E402
from forward.display import bmode_uint8, sector_fan  # noqa: E402
from forward.pairs import make_pair  # noqa: E402


bmode = bmode_uint8          # log-compressed 8-bit B-mode (50 dB), as tests/test_bmode.py
fan_of = sector_fan          # a sector's fan from an apex 20 mm above the first row


#: (name, pair factory, fan apex mm, fan half width at the top mm)
CASES = (
    ("L7 stiff inclusion 2 %, seed 2", lambda: make_pair(F.Inclusion("stiff", "plane-strain", 0.02, radius_mm=3.0),
                                                        "L7", (16.0, 14.0), 30.0, 2, top_mm=12.0), 20.0, 4.0),
    ("paper compression 1 %, seed 5", lambda: make_pair(F.compression(0.01), "paper", (24.0, 18.0), 20.0, 5),
     20.0, 4.0),
    ("L12 soft inclusion 1.5 %, seed 3", lambda: make_pair(F.Inclusion("soft", "plane-strain", 0.015,
                                                                       radius_mm=2.5),
                                                           "L12", (14.0, 14.0), 30.0, 3, top_mm=10.0), 15.0, 3.0),
    ("L7 shear + 1 % compression, seed 7", lambda: make_pair(F.shear_rotation(0.01, shear=0.005, rotation_deg=0.2),
                                                             "L7", (18.0, 16.0), 25.0, 7, top_mm=8.0), 25.0, 4.0),
    ("L7 stiff inclusion 2 %, seed 4", lambda: make_pair(F.Inclusion("stiff", "plane-strain", 0.02, radius_mm=3.0),
                                                        "L7", (16.0, 14.0), 30.0, 4, top_mm=12.0), 20.0, 4.0),
    ("L12 stiff inclusion 1 %, seed 8", lambda: make_pair(F.Inclusion("stiff", "plane-strain", 0.01, radius_mm=2.5),
                                                         "L12", (14.0, 14.0), 25.0, 8, top_mm=10.0), 15.0, 3.0),
    ("paper soft inclusion 1.5 %, seed 11", lambda: make_pair(F.Inclusion("soft", "plane-strain", 0.015,
                                                                          radius_mm=4.0),
                                                              "paper", (24.0, 20.0), 25.0, 11, top_mm=8.0), 25.0, 5.0),
    ("L7 compression 2 %, seed 9", lambda: make_pair(F.compression(0.02), "L7", (16.0, 16.0), 20.0, 9, top_mm=10.0),
     20.0, 4.0),
)


def strain_error(res, field, where):
    """(normalised axial strain error over the finite pixels inside ``where``, their fraction of ``where``)."""
    pts = res.pixel_points()
    e = res.strain(pts)[:, 0]
    ok = np.isfinite(e) & where.ravel()
    t = field.strain(pts[ok])[:, 0]
    return float(np.sqrt(np.mean((e[ok] - t) ** 2)) / np.mean(np.abs(t))), float(ok.sum() / where.sum())


def run_case(i, plain=True):
    name, make, apex, half = CASES[i]
    p = make()
    fan = fan_of(p.ref.shape, p.spacing, p.origin, apex, half)
    a, b = (np.where(fan, bmode(f), 0).astype(np.uint8) for f in (p.ref, p.mov))
    kw = dict(spacing=p.spacing, origin=p.origin, alpha="auto")
    rows = []
    t = time.perf_counter()
    r = femreg.register(a, b, **kw)
    rows.append(("register fan", r.auto_alpha.alpha, *strain_error(r, p.field, fan), time.perf_counter() - t))
    t = time.perf_counter()
    r = femreg.track(np.stack([a, b]), **kw)[-1]
    rows.append(("track fan", r.alpha, *strain_error(r, p.field, fan), time.perf_counter() - t))
    if plain:
        everywhere = np.ones(fan.shape, bool)
        for label, frames in (("B-mode no fill", (bmode(p.ref), bmode(p.mov))), ("RF", (p.ref, p.mov))):
            t = time.perf_counter()
            r = femreg.register(*frames, **kw)
            rows.append((f"register {label}", r.auto_alpha.alpha, *strain_error(r, p.field, everywhere),
                         time.perf_counter() - t))
    for call, alpha, err, cover, wall in rows:
        print(f"| {i} | {name} | {call} | {alpha:.4g} | {100 * err:.2f} | {100 * cover:.0f} | {wall:.1f} |",
              flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, nargs="+", default=list(range(len(CASES))))
    ap.add_argument("--no-plain", action="store_true", help="fan pairs only (no B-mode without fill, no RF)")
    args = ap.parse_args(argv)
    print("| case | pair | call | alpha | axial strain error % | covered % | wall s |")
    print("|---|---|---|---|---|---|---|")
    for i in args.cases:
        run_case(i, plain=not args.no_plain)


if __name__ == "__main__":
    main()
