"""Demo 02: simulated RF ultrasound sequences with known motion
============================================================

This demo shows how the paper's simulated image sequences are made and what they look like:

1. one forward solve of the phantom (3D, hard inclusion) at 1 mm patch compression,
2. point scatterers (30 per mm^2, Gaussian amplitudes, x2 inside the inclusion) moved by the FE displacement
   evaluated at the scatterer positions, scaled per frame by the compression schedule,
3. a separable PSF (5.5 MHz Gaussian-modulated pulse of -6 dB length 0.43 us, lateral FWHM 1.4 mm) rendered at
   each scatterer's exact position on a 0.01925 mm x 0.3 mm grid, plus white noise at SNR 12 dB.

Outputs (out/02_simulate/): ``bmode_frame1.png`` (B-mode of frame 1, the inclusion ROI outlined),
``true_strain_frame7.png`` (true axial and lateral strain frame 1 -> 7), and the compression schedule measured
from the true strain, printed.  ``--quick``: the plane-strain model with a coarser FE mesh and 7 frames.

The sequence comes from the disk cache when it exists (``femreg simulate`` fills it).
"""
import argparse
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import forward  # noqa: E402
from forward.sequences import schedule_figures  # noqa: E402
from femreg.plot import bmode  # noqa: E402

ap = argparse.ArgumentParser(description="simulated RF sequences: B-mode, true strain, schedule")
ap.add_argument("--quick", action="store_true", help="plane-strain model, coarse mesh, 7 frames")
args = ap.parse_args()
out = Path("out") / "02_simulate"  # relative to the working directory (run_all.py: the repository root)
out.mkdir(parents=True, exist_ok=True)

# ## The sequence
# `get_sequence` = `simulate_sequence` + a disk cache keyed by every parameter and the seed.
t0 = time.perf_counter()
if args.quick:
    seq = forward.get_sequence("plane-strain", "HI", n_frames=7, seed=0, snr_db=12.0,
                               fe_options={"mesh_size_mm": 1.5})
else:
    seq = forward.get_sequence("3d", "HI", n_frames=20, seed=0, snr_db=12.0)
print(f"sequence {seq.params['model']}/{seq.params['inclusion']}: {seq.frames.shape} frames, spacing "
      f"{seq.spacing} mm, origin {seq.origin} mm, field {seq.params['field_source']}, "
      f"{seq.params['n_scatterers']} scatterers ({time.perf_counter() - t0:.1f} s incl. cache)")
print(f"file: {seq.path}")

# ## Compression schedule, measured from the true strain
# Mean axial compressive strain -exx over the imaged area (frame-0 coordinates); frame 1 = index 0.
fig = schedule_figures(seq)
print("cumulative mean axial compressive strain per frame (%):", np.round(fig["cumulative"], 3).tolist())
print(f"total {fig['total']:.3f} %, mean step {fig['mean_step']:.3f} %, max step {fig['max_step']:.3f} %, "
      + ", ".join(f"{k.replace('frames_', '').replace('_', '->')} {fig[k]:.3f} %"
                  for k in ("frames_1_3", "frames_1_7", "frames_1_10") if k in fig))

# ## B-mode of frame 1 with the inclusion ROI
dx, dy = seq.spacing
x = seq.origin[0] + dx * np.arange(seq.shape[0])
y = seq.origin[1] + dy * np.arange(seq.shape[1])
extent = (y[0] - dy / 2, y[-1] + dy / 2, x[-1] + dx / 2, x[0] - dx / 2)
b = bmode(seq.frames[0], 50.0)
f, ax = plt.subplots(figsize=(4.2, 6.2))
im = ax.imshow(b, cmap="gray", extent=extent, aspect="equal", interpolation="none")
ax.contour(y, x, seq.inclusion_mask.astype(float), levels=[0.5], colors="r", linewidths=1.0)
ax.set(xlabel="lateral y (mm)", ylabel="depth x (mm)", title=f"B-mode, frame 1 ({seq.params['model']} HI)")
f.colorbar(im, ax=ax, label="dB", shrink=0.7)
f.tight_layout()
f.savefig(out / "bmode_frame1.png", dpi=120)
plt.close(f)

# ## True strain frame 1 -> 7 (frame index 6), on the pixel grid
k = min(6, seq.n_frames - 1)
eps = seq.true_strain(k, seq.pixel_points()).reshape(seq.shape + (3,))
f, axes = plt.subplots(1, 2, figsize=(8, 6.2))
for a, c, name in zip(axes, (0, 1), ("axial $\\epsilon_{xx}$", "lateral $\\epsilon_{yy}$")):
    v = 100 * eps[..., c]
    im = a.imshow(v, cmap="viridis", extent=extent, aspect="equal", interpolation="none")
    a.contour(y, x, seq.inclusion_mask.astype(float), levels=[0.5], colors="w", linewidths=0.8)
    a.set(xlabel="lateral y (mm)", ylabel="depth x (mm)", title=f"true {name}, frame 1 -> {k + 1}")
    f.colorbar(im, ax=a, label="%", shrink=0.7)
f.tight_layout()
f.savefig(out / "true_strain_frame7.png", dpi=120)
plt.close(f)
inside = eps[seq.inclusion_mask, 0].mean()
outside = eps[~seq.inclusion_mask, 0].mean()
print(f"true exx frame 1 -> {k + 1}: mean inside ROI {100 * inside:.3f} %, outside {100 * outside:.3f} %, "
      f"strain ratio outside/inside {outside / inside:.2f}")
print(f"wrote {out / 'bmode_frame1.png'} and {out / 'true_strain_frame7.png'}")
