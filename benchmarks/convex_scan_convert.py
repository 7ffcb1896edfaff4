"""Scan-convert first, or register in the native (range, angle) samples?  Convex pairs (forward.beam, 1 %
compression, two seeds) registered both ways, total strain error on the same points: the Gauss points of the
Cartesian rectangle inscribed in the fan (the scan-converted image's mesh).

* native: ``femreg.register(..., geometry=femreg.Convex(...))`` (the data term on the samples through the polar
  map, the mesh and the displacement Cartesian; docs/geometry.md);
* scan-converted: the RF interpolated (cubic B-spline in the sample indices) onto a Cartesian grid of the range
  step axially and ``--dy`` mm laterally inside the fan, registered as a linear-array frame (default alpha).

    python benchmarks/convex_scan_convert.py [--dy 0.1] [R/PITCH ...]     (default 40/0.3 50/0.45 60/0.6)
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import ndimage

import femreg
from femreg.metrics import field_errors, mesh_quadrature
from forward import fields as F
from forward.beam import make_beam_pair


def scan_convert(img, geo, dr, r0, dy):
    """RF (n_samples, n_rays) -> (image, spacing, origin) on the Cartesian rectangle inside the fan (one ray and
    one sample in from its edges)."""
    n_s, n_rays = img.shape
    R = geo.radius_mm
    thmax = geo.angles(n_rays)[-1] - geo.pitch_rad
    x_top = r0 + dr
    half = (R + x_top) * np.tan(thmax)
    x_bot = np.sqrt((R + r0 + (n_s - 2) * dr) ** 2 - half ** 2) - R
    x = np.arange(x_top, x_bot, dr)
    ny = int(2 * half / dy)
    y = (np.arange(ny) - 0.5 * (ny - 1)) * dy
    X, Y = np.meshgrid(x, y, indexing="ij")
    idx = geo.physical_to_index(np.column_stack([X.ravel(), Y.ravel()]), img.shape, (dr, 0), (r0, 0))
    out = ndimage.map_coordinates(ndimage.spline_filter(img, order=3), idx, order=3, prefilter=False)
    return out.reshape(X.shape), (dr, dy), (x[0], y[0])


def strain_error(res, pair, pts, w):
    """Total strain error (e:e with the shear twice) of ``res`` at points ``pts`` with weights ``w``."""
    d, t = res.strain(pts) - pair.true_strain(pts), pair.true_strain(pts)
    c = np.array([1.0, 1.0, 2.0])
    return float(np.sqrt(np.sum(w[:, None] * c * d ** 2) / np.sum(w[:, None] * c * t ** 2)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="*", default=["40/0.3", "50/0.45", "60/0.6"])
    ap.add_argument("--dy", type=float, default=0.1, help="lateral spacing of the scan-converted grid, mm")
    a = ap.parse_args(argv)
    print("| case | native, on the rectangle | native, whole fan | scan-converted, on the rectangle |\n"
          "|---|---|---|---|")
    for case in a.cases:
        R, pitch = (float(v) for v in case.split("/"))
        geo = femreg.Convex(R, pitch)
        for seed in (0, 1):
            p = make_beam_pair(F.compression(0.01), geo, depth_mm=40, n_rays=int(round(32 / pitch)), seed=seed)
            t = time.perf_counter()
            rn = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin, geometry=geo)
            tn = time.perf_counter() - t
            A, sp, org = scan_convert(p.ref, geo, p.spacing[0], p.origin[0], a.dy)
            B = scan_convert(p.mov, geo, p.spacing[0], p.origin[0], a.dy)[0]
            t = time.perf_counter()
            rs = femreg.register(A, B, spacing=sp, origin=org)
            ts = time.perf_counter() - t
            pts, w, _ = mesh_quadrature(rs.mesh, 3)
            whole = field_errors(rn, p.true_displacement, p.true_strain)["e"]
            print(f"| R{R:g} {pitch:g} deg, seed {seed} | {100 * strain_error(rn, p, pts, w):.2f} % ({tn:.1f} s) | "
                  f"{100 * whole:.2f} % | {100 * strain_error(rs, p, pts, w):.2f} % ({A.shape[0]} x {A.shape[1]}, "
                  f"{ts:.1f} s{'' if rs.success else ', FAILED'}) |", flush=True)


if __name__ == "__main__":
    main()
