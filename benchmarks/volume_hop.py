"""The volume peak-hopping check (:func:`femreg.volume.hop_check`) on the pairs of ``bench_volume.py``: the exact
field, and the exact field with u_x moved by +-one RF period over a block of hexahedra.  Prints the fraction of
elements flagged, the gains inside the block and the largest gain outside, and the check's CPU time.

    python benchmarks/volume_hop.py                  # 3, 7, 15 MHz
    python benchmarks/volume_hop.py --memory         # peak allocation of the check on a phantom-sized volume
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from femreg.repair import HOP_GAIN, envelope_lag_ncc_3d, hopped_fraction, lag_gain  # noqa: E402
from femreg.volume import _rf_period_3d  # noqa: E402
from femreg.voxels import VOXEL_DTYPE, SplineVolume, VoxelGrid, VoxelSSDTerm, roi_mesh_3d  # noqa: E402


def doctored(probes, cache):
    import bench_volume as bv

    for f in probes:
        path, G = bv._pair((800, 100, 60), f, 0, 40.0, cache)
        with np.load(path) as z:
            ref, mov, spacing = z["ref"].astype(float), z["mov"].astype(float), tuple(z["spacing"])
        ref /= np.sqrt(np.mean(ref ** 2))
        mov /= np.sqrt(np.mean(mov ** 2))
        centre = np.array(ref.shape) * np.array(spacing) / 2
        T = _rf_period_3d(ref, spacing)
        mesh = roi_mesh_3d(ref.shape, spacing)
        data = VoxelSSDTerm(VoxelGrid(mesh, ref.shape, spacing, np.zeros(3)), SplineVolume(ref, spacing),
                            SplineVolume(mov, spacing, keep_data=False))
        del ref, mov
        truth = ((mesh.p.T - centre) @ G.T).ravel()
        g = lag_gain(envelope_lag_ncc_3d(data, data.warped_moving(truth), T))
        print(f"{f:g} MHz (T {T:.4f} mm), exact field: {100 * hopped_fraction(g):.1f} % of {g.size} elements "
              f"flagged, largest gain {np.nanmax(g):.2f}", flush=True)
        p = mesh.p
        blocks = {"6 x 6 x 5 mm": (np.abs(p[0] - 10) < 3.1) & (np.abs(p[1] - 10) < 3.1) & (np.abs(p[2] - 7.5) < 2.6),
                  "8 x 8 mm, all z": (np.abs(p[0] - 5) < 4.1) & (np.abs(p[1] - 14) < 4.1)}
        for name, blk in blocks.items():
            inside = blk[mesh.t].all(axis=0)
            apart = ~blk[mesh.t].any(axis=0)
            for sign in (1, -1):
                u = truth.copy()
                u[0::3][blk] += sign * T
                b = data.warped_moving(u)
                c0 = time.process_time()
                g = lag_gain(envelope_lag_ncc_3d(data, b, T))
                cpu = time.process_time() - c0
                print(f"  block {name}, u_x {sign:+d} T: {100 * hopped_fraction(g):.1f} % flagged ({inside.sum()} "
                      f"elements wholly inside, {100 * np.mean(g[inside] > HOP_GAIN):.0f} % of them flagged, gains "
                      f"{np.nanmin(g[inside]):.2f}-{np.nanmax(g[inside]):.2f}); largest gain outside "
                      f"{np.nanmax(g[apart]):.2f}; check {cpu:.3f} s CPU", flush=True)


def memory():
    """The check on a synthetic volume of the paper phantom's size (carrier-modulated noise as both volumes)."""
    class Data:
        pass

    shape, spacing = (3740, 147, 41), (0.0125, 0.2, 0.5)
    mesh = roi_mesh_3d(shape, spacing)
    d = Data()
    d.grid = VoxelGrid(mesh, shape, spacing, np.zeros(3))
    d.shape = d.grid.block_shape
    x = np.arange(d.shape[0])[:, None, None] * spacing[0]
    rng = np.random.default_rng(0)
    d.ref_values = (np.cos(4 * np.pi * 7.0 / 1.54 * x) * rng.standard_normal(d.shape)).astype(VOXEL_DTYPE)
    w = d.ref_values.astype(float)
    tracemalloc.start()
    c0 = time.process_time()
    g = lag_gain(envelope_lag_ncc_3d(d, w, 0.11))
    cpu = time.process_time() - c0
    print(f"{d.grid.n_voxels} voxels in {mesh.t.shape[1]} elements: check {cpu:.2f} s CPU, peak allocation "
          f"{tracemalloc.get_traced_memory()[1] / 1e6:.0f} MB (the warped volume: {w.nbytes / 1e6:.0f} MB); "
          f"{100 * hopped_fraction(g):.1f} % flagged")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--probes", type=float, nargs="+", default=[3.0, 7.0, 15.0])
    ap.add_argument("--cache", default=os.environ.get("FEMREG_CACHE", tempfile.gettempdir()))
    ap.add_argument("--memory", action="store_true")
    a = ap.parse_args(argv)
    if a.memory:
        memory()
    else:
        doctored(a.probes, a.cache)


if __name__ == "__main__":
    main()
