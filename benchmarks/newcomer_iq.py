"""A newcomer's recording: beamformed IQ frames of a 5 MHz linear probe saved from MATLAB as a Verasonics-style
MAT-file (``IData`` and ``QData``, real arrays ``(axial, lateral, frame)``, beside the ``Trans`` and ``Receive``
structs that hold the probe's and the receiver's settings), registered from the command line and measured against
its exact truth.

Probe 5.208 MHz (an L7-4-like array), 128 lines at 0.298 mm (38.1 mm), RF sampled at 20.83 MHz (4 samples per
period), 1.0 mm beam; 0-60 mm of depth, full depth, no crop, echo attenuated without TGC into the noise floor at
48 mm (SNR 30 dB at the face).  The IQ: the RF's analytic signal shifted down by the demodulation frequency
(5.208 MHz) and decimated 2x (10.42 MHz, 0.0739 mm per sample), stored as single.  Tissue: the FE model of a 4x
stiffer 10 mm disk 20 mm deep in a compressed block (:class:`forward.fields.Inclusion`, plane strain), 6 frames at
0.5 % compression per frame.

The header as the scanner states it: ``Trans.frequency`` 5.208 (MHz), ``Trans.spacingMm`` 0.298,
``Receive.demodFrequency`` 5.208 (MHz), ``Receive.decimSampleRate`` 20.832 (MHz: the RF sampling rate, before
the IQ's 2x decimation), ``Receive.startDepth`` 0.  The honest mistake: the axial spacing of the header's rate,
``c / (2 fs)`` = 0.036962 mm, half the IQ samples' step.

Prints each command's exit code, time and last lines, and for the results the errors against the truth over the
echo (depth 2-44 mm, 1.5 mm from the sides): u RMS error (um), e_xx error relative to the true e_xx's RMS, the
total strain error (e_xx, e_yy, 2 e_xy), and the disk's strain ratio (ring 6.5-9 mm / disk 3.5 mm) against the
true one.

Measured (2026-12-08, 2 shared cores; 161 s in all): ``info`` exit 1 suggesting ``--spacing 0.07392 0.298`` (the
IQ decimation read from the phases of frames 0 and 1) and ``--iq-frequency 5.208``; with them exit 0.  The header
rate's spacing (0.036962) refused, exit 2, naming ``--spacing 0.073925 0.298`` (the phases turn as for 10.3 MHz at
it); ``--iq-frequency 10.416`` (what the phases show at that spacing) refused against the file's 5.208.  Past the
checks (``--no-orientation-check``) that pair registers with success, frames 30 mm deep (true 60), largest |u_x|
0.125 mm (0.25 in truth), median e_xx -0.583 %: strain right, every length halved.  register 0 -> 1 (0.5 %): 9 s,
total 5.9 %, e_xx 4.4 % (median -0.582 %, true -0.585 %), u RMS 0.3 / 1.5 um, SR 2.53 (true 2.51), the echo found
to 44.3 mm (floor at 48).  track 0 -> 5 (19 s, none flagged): 7.7 %, e_xx 6.0 % (median -2.919 %, true -2.925 %),
u RMS 1.7 / 7.2 um, SR 2.44 (true 2.51).  elastogram: 3 of 3 pairs usable, best on frame 2, 18 s.  Before: the
file was refused ("several 2D/3D variables (IData, QData)"); ``--variable IData`` read the in-phase half as real
data with "no spacing found" and no suggestion; the header rate's spacing was refused as a wrong demodulation
frequency ("turns as for a 10.3 MHz demodulation ... give the demodulation frequency the scanner recorded"), and
following that advice (``--iq-frequency 10.3``) registered as above, halved, exit 0.

Run: ``OMP_NUM_THREADS=1 python benchmarks/newcomer_iq.py [OUTDIR] [--skip-track] [--skip-elastogram]``.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))      # after PYTHONPATH: it chooses the femreg measured
from forward.fields import Inclusion  # noqa: E402
from newcomer_msk import femreg_cli as _femreg_cli, walk_args  # noqa: E402
from forward.pairs import Probe, alpha_for_floor, attenuation_gain_db, make_sequence  # noqa: E402

N, STEP = 6, 0.005                               # frames, compression per frame
F0, C, PITCH, LINES = 5.208, 1540.0, 0.298, 128  # MHz, m/s, mm
FS_RF, DECIM = 4 * F0, 2                         # RF sampling (MHz), IQ decimation
FS_IQ = FS_RF / DECIM
PROBE = Probe(F0, FS_RF, PITCH, 1.0, 2.0, name="L7-4", c_m_s=C)
DEPTH, WIDTH = 60.0, LINES * PITCH
SNR, FLOOR = 30.0, 48.0
DX_IQ = C * 1e-3 / (2 * FS_IQ)                   # mm per IQ sample


def render(seed=0):
    """The RF sequence (forward.pairs.SequencePair), 0-60 mm."""
    field = Inclusion("stiff", "plane-strain", 0.0)
    gain = attenuation_gain_db(alpha_for_floor(FLOOR, SNR, F0), F0)
    return make_sequence(field, PROBE, (DEPTH, WIDTH), SNR, seed, n_frames=N, step=STEP, top_mm=0.0,
                         echo_gain_db=gain)


def to_iq(rf, dx):
    """(n, axial, lateral) RF -> IQ at FS_IQ: analytic signal shifted down by F0, decimated DECIM x."""
    from scipy.signal import hilbert, resample_poly

    z = dx * np.arange(rf.shape[1])
    iq = hilbert(rf, axis=1) * np.exp(-2j * np.pi * F0 * 2e3 * z / C)[None, :, None]
    return resample_poly(iq, 1, DECIM, axis=1)


def write(out, seq, name="abdo_iq"):
    """The MAT-file a MATLAB user saves after a Verasonics acquisition; returns its path."""
    import scipy.io

    iq = to_iq(np.asarray(seq.frames, float), seq.spacing[0])
    iq = iq / np.abs(iq).max()
    iq_m = np.moveaxis(iq, 0, -1)                  # MATLAB: (axial, lateral, frame)
    path = Path(out) / f"{name}.mat"
    scipy.io.savemat(str(path), {
        "IData": iq_m.real.astype(np.float32), "QData": iq_m.imag.astype(np.float32),
        "Trans": {"name": "L7-4", "frequency": F0, "spacingMm": PITCH, "numelements": float(LINES)},
        "Receive": {"demodFrequency": F0, "decimSampleRate": FS_RF, "startDepth": 0.0},
    })
    return path



FIELD = None


def truth():
    """forward.fields.LoopTruth of the loop: frame k images the frame-0 point X at X + u_k(X)."""
    from forward.fields import LoopTruth

    global FIELD
    if FIELD is None:
        FIELD = Inclusion("stiff", "plane-strain", 0.0)
    fields = [FIELD.at(k * STEP) for k in range(N)]
    return LoopTruth(lambda k, X: np.asarray(X, float) + fields[k].displacement(X))


def errors(path, i, j, y_first):
    """Errors of a femreg result file against the truth of frame i -> j (frame-i coordinates); ``y_first``: the
    truth's lateral position of the file's first line (femreg puts it at 0: the file has no origin)."""
    import femreg

    res = femreg.load_result(path)
    g = res.on_grid()
    P = res.pixel_points() + np.array([0.0, y_first])
    est = np.stack([g["exx"], g["eyy"], g["exy"]], -1).reshape(-1, 3)
    u = np.stack([g["ux"], g["uy"]], -1).reshape(-1, 2)
    ok = (np.all(np.isfinite(est), 1) & (P[:, 0] > 2.0) & (P[:, 0] < 44.0)
          & (np.abs(P[:, 1]) < 0.5 * WIDTH - 1.5))
    if not ok.any():
        return None
    P, est, u = P[ok][::3], est[ok][::3], u[ok][::3]
    T = truth()
    t, tu = T.strain(i, j, P), T.displacement(i, j, P)
    w = np.array([1.0, 1.0, 2.0])
    (xc, yc), = T.motion(i, np.array([[20.0, 0.0]]))
    r = np.hypot(P[:, 0] - xc, P[:, 1] - yc)
    inl, bg = r < 3.5, (r > 6.5) & (r < 9.0)
    return dict(total=100 * math.sqrt(np.sum(w * (est - t) ** 2) / np.sum(w * t ** 2)),
                exx=100 * math.sqrt(np.sum((est[:, 0] - t[:, 0]) ** 2) / np.sum(t[:, 0] ** 2)),
                ux_um=1e3 * math.sqrt(np.mean((u[:, 0] - tu[:, 0]) ** 2)),
                uy_um=1e3 * math.sqrt(np.mean((u[:, 1] - tu[:, 1]) ** 2)),
                exx_mean=100 * float(np.median(est[:, 0])), exx_true=100 * float(np.median(t[:, 0])),
                sr=est[bg, 0].mean() / est[inl, 0].mean(), sr_true=t[bg, 0].mean() / t[inl, 0].mean(),
                success=bool(res.success), reach_mm=float(P[:, 0].max()))


def say(name, e):
    if e is None:
        print(f"  {name}: nothing registered in the echo")
        return
    print(f"  {name}: total {e['total']:5.1f} %, e_xx {e['exx']:5.1f} % (median {e['exx_mean']:.3f} %, true "
          f"{e['exx_true']:.3f} %), u RMS {e['ux_um']:.1f} / {e['uy_um']:.1f} um, SR {e['sr']:.2f} (true "
          f"{e['sr_true']:.2f}), reach {e['reach_mm']:.1f} mm, success {e['success']}", flush=True)


def femreg_cli(*args):
    """:func:`newcomer_msk.femreg_cli`, its lines shown up to 400 characters (the IQ refusals are long)."""
    return _femreg_cli(*args, width=400)


def main(argv=None):
    a, out = walk_args(argv, __doc__, "newcomer_iq_")
    t = time.perf_counter()
    seq = render()
    mat = write(out, seq)
    y_first = float(seq.origin[1])
    print(f"wrote {mat} in {time.perf_counter() - t:.1f} s: IQ {DX_IQ:.5g} mm x {PITCH} mm, {N} frames")
    right = ["--spacing", f"{DX_IQ:.5g}", f"{PITCH}", "--iq-frequency", f"{F0}", "--no-progress"]
    femreg_cli("info", mat)
    femreg_cli("info", mat, *right)
    # the honest mistake: the axial spacing of the header's sampling rate, c / (2 fs), for IQ decimated 2x
    femreg_cli("register", mat, "--pair", 0, 1, "-o", out / "rate.npz", "--spacing", f"{C * 1e-3 / (2 * FS_RF):.5g}",
               f"{PITCH}", "--iq-frequency", f"{F0}")
    # the advice the refusal gave before: the frequency the phases show at that spacing
    wrong = ["--spacing", f"{C * 1e-3 / (2 * FS_RF):.5g}", f"{PITCH}", "--iq-frequency", f"{2 * F0:.5g}"]
    femreg_cli("register", mat, "--pair", 0, 1, "-o", out / "advice.npz", *wrong)
    femreg_cli("register", mat, "--pair", 0, 1, "-o", out / "advice.npz", *wrong, "--no-orientation-check",
               "--no-progress")
    if (out / "advice.npz").exists():
        import femreg

        res = femreg.load_result(out / "advice.npz")
        g, P = res.on_grid(), res.pixel_points()
        T = truth()
        tu = T.displacement(0, 1, np.array([[40.0, 0.0]]))[0, 0]
        print(f"  as before, following it: success {res.success}, frames {P[:, 0].max():.1f} mm deep (true "
              f"{DEPTH:g}), largest |u_x| {np.nanmax(np.abs(g['ux'])):.3f} mm (true u_x at 40 mm {tu:.3f}), median "
              f"e_xx {100 * np.nanmedian(g['exx']):.3f} %")
    femreg_cli("register", mat, "--pair", 0, 1, "-o", out / "p01.npz", *right)
    if (out / "p01.npz").exists():
        say("register 0 -> 1", errors(out / "p01.npz", 0, 1, y_first))
    femreg_cli("plot", out / "p01.npz", "--reference", mat, *right)
    if not a.skip_track:
        femreg_cli("track", mat, "-o", out / "run", *right)
        last = out / "run" / f"frame_{N - 1:03d}.npz"
        if last.exists():
            say(f"track 0 -> {N - 1}", errors(last, 0, N - 1, y_first))
            femreg_cli("plot", last, "--reference", mat, *right)
    if not a.skip_elastogram:
        femreg_cli("elastogram", mat, "-o", out / "loop", *right)
    print(f"outputs in {out}")


if __name__ == "__main__":
    main()
