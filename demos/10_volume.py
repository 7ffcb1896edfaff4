r"""Demo 10: RF volumes -- simulate a volume pair, register it in 3D, look at it in three orthogonal slices
==========================================================================================================

This demo shows how to

* simulate RF volumes of a matrix-array (or mechanically swept) probe with ``forward.volume``: a Gaussian-modulated
  pulse, lateral and elevational beams with a depth focus (a 2 mm elevational beam), stratified scatterers per
  mm^3, white noise at a stated SNR, and the *same* scatterers moved by an exact 3D field for the second volume;
* register the pair with ``femreg.register`` on ``(axial, lateral, elevational)`` arrays with
  ``spacing=(dx, dy, dz)`` (when the installed femreg registers volumes; otherwise the demo says so and draws the
  true fields), and compare the six strain components with the truth;
* draw three orthogonal slices (B-mode, displacement, strain, quality) with ``femreg.volplot`` and an off-screen
  pyvista rendering.

The field: an affine 3D deformation, 1 % axial compression with the incompressible lateral and elevational
expansion (0.5 % each), a 0.3 % e_xy shear and a 0.5 degree rotation about the elevational axis.

Output: ``out/10_volume/`` -- ``slices.png`` (reference B-mode and the fields), ``render.png`` (pyvista slices of
e_xx, when pyvista is installed), ``summary.md``.
Run: ``python demos/10_volume.py [--quick]`` (``--quick``: a 10 x 8 x 10 mm volume instead of 20 x 20 x 15 mm).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

import femreg  # noqa: E402
from femreg.errors import InputError  # noqa: E402
from femreg.volplot import STRAIN_KEYS, plot_volume_slices, render_volume  # noqa: E402
from forward.volume import VOLUME_PROBES, Affine3D, make_volume_pair  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.splitlines()[1] if __doc__ else "RF volumes")
ap.add_argument("--quick", action="store_true", help="a 10 x 8 x 10 mm volume (seconds)")
args = ap.parse_args()
out = Path("out") / "10_volume"
out.mkdir(parents=True, exist_ok=True)
lines = ["# Demo 10: RF volumes", ""]

# ## The volume pair
# The 7 MHz matrix-array preset: axial 0.025 mm (30.8 MHz), lateral lines 0.2 mm, elevational planes 0.25 mm,
# beams 0.9 mm (lateral, dynamic focus) and 2 mm (elevational, lens focus at 20 mm), 30 dB SNR.
size = (10.0, 8.0, 10.0) if args.quick else (20.0, 20.0, 15.0)
field = Affine3D(0.01, shear={"xy": 0.003}, rotation_deg=(0.0, 0.0, 0.5), centre=(2.0 + size[0] / 2, 0.0, 0.0))
t0 = time.perf_counter()
pair = make_volume_pair(field, VOLUME_PROBES["matrix7"], size, top_mm=2.0, snr_db=30.0, seed=0)
t_sim = time.perf_counter() - t0
print(f"volume pair {pair.ref.shape} voxels, spacing {tuple(round(s, 4) for s in pair.spacing)} mm, "
      f"{pair.params['n_scatterers']} scatterers, rendered in {t_sim:.1f} s")
lines += [f"- volume pair: {pair.ref.shape} voxels (axial, lateral, elevational), spacing "
          f"{tuple(round(s, 4) for s in pair.spacing)} mm, {pair.params['n_scatterers']} scatterers, "
          f"{t_sim:.1f} s to simulate", ""]

# ## Registration in 3D
# The true fields on the voxel grid, for the comparison (and for the pictures when femreg cannot register
# volumes).
grid = pair.grid
P = grid.points()
U = field.displacement(P).reshape(grid.shape + (3,))
E = field.strain(P).reshape(grid.shape + (6,))
truth = {"ux": U[..., 0], "uy": U[..., 1], "uz": U[..., 2], **{k: E[..., i] for i, k in enumerate(STRAIN_KEYS)}}
result = None
try:
    t0 = time.perf_counter()
    result = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin)
    t_reg = time.perf_counter() - t0
except InputError as exc:
    if "2D" not in str(exc):
        raise
    print(f"femreg.register does not register volumes in this version ({exc}); drawing the true fields")
    lines += ["- registration: not available in this femreg version (femreg.register takes 2D frames only); the "
              "pictures show the true fields", ""]
if result is not None:
    fields = result.on_grid()
    # total strain error over the six components (shear counted twice) in the interior (1 mm margin)
    m = [max(1, int(round(1.0 / d))) for d in grid.spacing]
    inner = tuple(slice(a, n - a) for a, n in zip(m, grid.shape))
    w = np.array([1, 1, 1, 2, 2, 2], float)
    em = np.stack([fields[k][inner] for k in STRAIN_KEYS], -1)
    et = E[inner]
    ok = np.all(np.isfinite(em), axis=-1)
    err = float(np.sqrt(np.sum(w * (em[ok] - et[ok]) ** 2) / np.sum(w * et[ok] ** 2)))
    print(f"registered in {t_reg:.1f} s: success {result.success}, total strain error {100 * err:.2f} % "
          f"(six components, interior)")
    lines += [f"- registration: {t_reg:.1f} s, success {result.success} ({result.message})",
              f"- total strain error (six components, shear twice, 1 mm margin): {100 * err:.2f} %", ""]
else:
    fields = truth
title = "registered" if result is not None else "true fields (no volume registration in this femreg)"

# ## Three orthogonal slices
# Axial-lateral (the scanner's B-mode plane), axial-elevational and lateral-elevational (a C-plane) through the
# centre; strains in %, one colour bar per row.
keys = ["ux", "uz", "exx", "ezz", "exy"] + (["quality"] if "quality" in fields else [])
fig = plot_volume_slices(fields, grid.spacing, grid.origin, reference=pair.ref, keys=keys,
                         out_png=out / "slices.png", title=f"Demo 10: {title}")
print(f"wrote {out / 'slices.png'}")

# ## A 3D rendering
try:
    render_volume(fields, grid.spacing, grid.origin, out / "render.png", key="exx", mode="slices")
    print(f"wrote {out / 'render.png'}")
except ImportError as exc:          # femreg.optional.MissingDependencyError: pyvista not installed
    print(f"no 3D rendering: {exc}")
(out / "summary.md").write_text("\n".join(lines) + "\n")
print(f"wrote {out / 'summary.md'}")
