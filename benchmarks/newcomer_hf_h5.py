"""A newcomer's recording: a 15 MHz linear probe's cine loop as a research scanner's HDF5 export (``rf``: int16
frames first, ``(frame, axial, lateral)``; ``timestamps``: one per frame, s; the acquisition as file attributes
in Hz, m/s and m), full depth 0-30 mm, registered from the command line with the honest mistake of the axial and
lateral spacings exchanged, then right, and measured against its FE truth.

Probe 15 MHz, 60 MHz sampling (0.01283 mm), 0.1 mm pitch, 0.3 mm beam, 128 lines (12.8 mm); the echo attenuated
without TGC into the noise floor at 26 mm (SNR 30 dB at the face).  Tissue: the FE model of a 4x stiffer 10 mm
disk 20 mm deep (:class:`forward.fields.Inclusion`, plane strain), 4 frames at 0.4 % compression per frame.

Prints each command's exit code, time and last lines, and the errors over the echo (depth 1-23 mm, 1 mm from the
sides): total strain error (e_xx, e_yy, 2 e_xy), e_xx error, both relative to the truth's RMS, and median e_xx.

Measured (2026-12-08, 2 shared cores, 70 s): ``info`` exit 1 suggesting ``--spacing 0.01283 0.1``; ``register``
with ``--spacing 0.1 0.01283`` exit 2 naming the swap and ``--spacing 0.01283 0.1`` (before: "the echo region
-0.01 to 1.64 mm is too small for a mesh inside the margin (78 pixels) along axis 1: depth below 193.0 mm
excluded ...", no word of the swap; ``track`` / ``elastogram`` first noted "the RF carrier reads 1.93 MHz ... the
axial spacing is too large"); right: register 0 -> 1 total 16.7 %, e_xx 13.4 % (median -0.496 %, true -0.509 %),
the echo found to 24.8 mm; track 0 -> 3 total 19.5 %, e_xx 14.7 % (median -1.483 %, true -1.526 %); elastogram 1
of 3 candidate pairs registered and usable.

Run: ``OMP_NUM_THREADS=1 python benchmarks/newcomer_hf_h5.py [OUTDIR]``.
"""
from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.append(str(HERE))
from newcomer_iq import femreg_cli  # noqa: E402  (also puts the repository on the path)

from forward.fields import Inclusion, LoopTruth  # noqa: E402
from forward.pairs import Probe, alpha_for_floor, attenuation_gain_db, make_sequence  # noqa: E402

N, STEP = 4, 0.004
F0, FS, PITCH, LINES, C = 15.0, 60.0, 0.1, 128, 1540.0
DEPTH, WIDTH, SNR, FLOOR = 30.0, LINES * PITCH, 30.0, 26.0
DX = C * 1e-3 / (2 * FS)


def write(out):
    seq = make_sequence(Inclusion("stiff", "plane-strain", 0.0), Probe(F0, FS, PITCH, 0.3, 2.0, name="L15"),
                        (DEPTH, WIDTH), SNR, 1, n_frames=N, step=STEP, top_mm=0.0,
                        echo_gain_db=attenuation_gain_db(alpha_for_floor(FLOOR, SNR, F0), F0))
    import h5py

    fr = np.asarray(seq.frames)
    path = Path(out) / "hf.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("rf", data=np.round(fr * (20000 / np.abs(fr).max())).astype("<i2"))
        f.create_dataset("timestamps", data=1.7e9 + 0.025 * np.arange(N) + np.array([0, 4e-4, -2e-4, 1e-4])[:N])
        f.attrs.update(sampling_frequency=FS * 1e6, center_frequency=F0 * 1e6, element_pitch=PITCH * 1e-3,
                       sound_speed=C)
    return path, seq


def errors(path, i, j, seq):
    import femreg

    fields = [Inclusion("stiff", "plane-strain", 0.0).at(k * STEP) for k in range(N)]
    T = LoopTruth(lambda k, X: np.asarray(X, float) + fields[k].displacement(X))
    r = femreg.load_result(path)
    g, P = r.on_grid(), r.pixel_points() + np.array([0.0, seq.origin[1]])
    e = np.stack([g["exx"], g["eyy"], g["exy"]], -1).reshape(-1, 3)
    ok = np.all(np.isfinite(e), 1) & (P[:, 0] > 1) & (P[:, 0] < 23) & (np.abs(P[:, 1]) < 0.5 * WIDTH - 1)
    P, e = P[ok][::3], e[ok][::3]
    t, w = T.strain(i, j, P), np.array([1.0, 1.0, 2.0])
    print(f"  {path.name} {i} -> {j}: total {100 * math.sqrt(np.sum(w * (e - t) ** 2) / np.sum(w * t ** 2)):.1f} %, "
          f"e_xx {100 * math.sqrt(np.sum((e[:, 0] - t[:, 0]) ** 2) / np.sum(t[:, 0] ** 2)):.1f} % (median "
          f"{100 * np.median(e[:, 0]):.3f} %, true {100 * np.median(t[:, 0]):.3f} %), success {r.success}")


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="newcomer_hf_"))
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    path, seq = write(out)
    print(f"wrote {path} in {time.perf_counter() - t:.1f} s")
    right, swapped = ["--spacing", f"{DX:.5g}", f"{PITCH}"], ["--spacing", f"{PITCH}", f"{DX:.5g}"]
    femreg_cli("info", path)
    for cmd, o in (("register", ["-o", out / "s.npz", "--pair", 0, 1]), ("track", ["-o", out / "srun"]),
                   ("elastogram", ["-o", out / "sloop"])):
        femreg_cli(cmd, path, *swapped, *o, "--no-progress")
    femreg_cli("register", path, *right, "-o", out / "r.npz", "--pair", 0, 1, "--no-progress")
    if (out / "r.npz").exists():
        errors(out / "r.npz", 0, 1, seq)
    femreg_cli("track", path, *right, "-o", out / "run", "--no-progress")
    last = out / "run" / f"frame_{N - 1:03d}.npz"
    if last.exists():
        errors(last, 0, N - 1, seq)
    femreg_cli("elastogram", path, *right, "-o", out / "loop", "--no-progress")
    print(f"outputs in {out}")


if __name__ == "__main__":
    main()
