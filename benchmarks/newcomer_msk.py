"""A newcomer's recording: a freehand musculoskeletal cine loop of a 15 MHz linear hand-held probe, written as a
Clarius research export (``*_rf.raw`` + ``*_rf.yml``), registered from the command line and measured against its
exact truth.

Probe 15 MHz, 40 MHz sampling (0.01925 mm), 0.1 mm pitch, 0.3 mm beam, 256 lines (25.6 mm), 0-40 mm of depth
(2078 samples, full depth, no crop); the echo attenuated without TGC into the noise floor at 25 mm (SNR 32 dB at
the face).  Tissue: a bright skin line (0-1 mm), hypoechoic subcutaneous fat (1-9.5 mm), a fascia band 1 mm thick
at 10 mm across which the muscle below slides laterally under the fat (``forward.fields.ShearBand``: 0-40 um per
frame, the clinical signal), muscle below, and a small stiff nodule (Gaussian, r 2 mm, centre strain x0.4) at
16 mm.  24 frames of freehand motion: uneven compression steps of 0.1-1.5 % per frame, three frames nearly still
(0.01 %), one jolt (frame 15: 1.5 % with 0.4 mm of lateral slip and 0.1 mm out of plane), small drift otherwise;
0.5 mm elevational beam.

Written as the Clarius raw format: a header of 5 little-endian int32 (id, frames, lines, samples, sample size in
bytes), then per frame an int64 time stamp (ns) and ``lines x samples`` int16, line after line; beside it a YAML
file of the settings (sampling rate, probe pitch, ...).

Prints the wall time and exit code of each command, and for the results the errors against the truth over the
registered echo (depth 1-22 mm, 1 mm from the sides): u RMS error (um), e_xx error relative to the true e_xx's
RMS, the total strain error (e_xx, e_yy, 2 e_xy), the nodule's strain ratio (ring 3-4.5 mm / disk 1.2 mm) against
the true one, and the slide across the fascia (lateral displacement 2 mm below the band's centre minus 2 mm above,
median) against the truth.

Measured (2026-12-07, 2 shared cores; rendering 3 min, the commands 4 min): ``info`` exit 1 naming ``--spacing
0.01925 0.1`` from the YAML, exit 0 with it; the swapped spacing (``--spacing 0.1 0.01925``) refused, exit 2, with
the right one; the pitch typed in metres (``0.0001``) refused as units, exit 2.  The echo found to 24.0-24.1 mm.
register 2 -> 3 (0.75 %): 10 s, total 41.2 %, e_xx 8.3 %, u RMS 1.0 / 6.4 um, SR 1.01 (true 2.16), slide 7.3 um
(true 24.7); ``--alpha auto`` chose 0.42: the same (SR 1.00, 7.1 um); ``--alpha 0.00133``: 31.7 %, 8.0 %, 0.4 /
2.0 um, SR 1.55, 22.3 um.  register 14 -> 15 (the jolt, 1.5 % and 0.4 mm slip): 17.7 %, 8.5 %, 2.0 / 5.2 um, SR
1.04 (true 2.29), slide 6.2 um (true 18.0).  ``measure --slide`` at the band +-2 mm: 7.3 / 22.4 um.  track 0 -> 11
(42 s, none flagged, 4 increments retried from a fresh start, the still frames at the iteration limit;
since a still frame after a moving one starts afresh, frames 0-11 through femreg.track on the same quantised frames:
3 and 5 iterations, their increments' lateral error 23.4 / 18.4 -> 4.2 / 4.3 um, 0 -> 11 u RMS 10.3 / 53.7 um, slide
61.7 um, total and e_xx unchanged): 34.1 %,
e_xx 8.2 %, u RMS 10.1 / 71.5 um, SR 1.01 (true 2.14), slide 51.6 um (true 213.2).  elastogram: 15 pairs
registered, 13 usable, best on frame 15 (after the jolt), 36 s; its colours span 5.6 % of the mean, the nodule's
SR 1.03.  Before ``femreg.io.clarius`` the file could not be read (``needs --shape``; with the shape, 212 bytes
over the frames, unexplained).

Run: ``OMP_NUM_THREADS=1 python benchmarks/newcomer_msk.py [OUTDIR] [--skip-track] [--skip-elastogram]`` (about
7 minutes on one core).
"""
from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))      # after PYTHONPATH: it chooses the femreg measured
from forward.fields import LoopTruth, ShearBand  # noqa: E402
from forward.pairs import Probe, _grid, alpha_for_floor, attenuation_gain_db, elevation_scatterers  # noqa: E402
from forward.ultrasound import render_elevation_loop  # noqa: E402

N = 24                                          # frames
F0, FS, PITCH, C = 15.0, 40.0, 0.1, 1540.0      # MHz, MHz, mm, m/s
LINES = 256
PROBE = Probe(F0, FS, PITCH, 0.3, 2.0, name="L15 hand-held", c_m_s=C)
DEPTH, WIDTH, TOP = 40.0, LINES * PITCH, 0.0    # mm
SNR, FLOOR = 32.0, 25.0                         # dB at the face; depth (mm) where the echo meets the noise
SIG_E = 0.5                                     # elevational beam, mm
NOD = dict(xc=16.0, yc=2.0, R=2.0, beta=-0.6)   # stiff nodule: centre strain x0.4
SKIN, FAT = 1.0, 9.5                            # skin 0-1 mm, fat 1-9.5 mm
BAND = (10.0, 1.0)                              # fascia: centre depth, thickness (mm)
_rng = np.random.default_rng(2026)
STEP = _rng.uniform(0.1, 1.5, N - 1) / 100      # compression per frame, fraction
STEP[[4, 9, 19]] = 0.0001                       # the hand holds still
JOLT = 15                                       # frame k = 15: a jolt
STEP[JOLT - 1] = 0.015
COMP = np.r_[0.0, np.cumsum(STEP)]
DRIFT = np.r_[0.0, np.cumsum(_rng.normal(0.01, 0.01, N - 1))]         # probe's lateral drift, mm
DRIFT[JOLT:] += 0.4                                                   # lateral slip of the jolt
SLIDE = np.r_[0.0, np.cumsum(_rng.uniform(0.0, 0.04, N - 1))]         # muscle under the fat, mm
ELEV = np.r_[0.0, np.cumsum(np.abs(_rng.normal(0.0, 0.015, N - 1)))]  # out of plane, mm
ELEV[JOLT:] += 0.1


def U(p):
    """Displacement per unit compression (mm): uniform towards the face, a Gaussian stiff bump, lateral y / 2."""
    dx, dy = p[:, 0] - NOD["xc"], p[:, 1] - NOD["yc"]
    g = np.exp(-(dx ** 2 + dy ** 2) / (2 * NOD["R"] ** 2))
    return np.column_stack([-(p[:, 0] + NOD["beta"] * dx * g), 0.5 * p[:, 1]])


def motion(k, X):
    """Where frame k images the tissue point X (frame-0 coordinates, mm)."""
    m = X + COMP[k] * U(X) + ShearBand(BAND[0], BAND[1], SLIDE[k], 0.0).displacement(X)
    m[:, 1] -= DRIFT[k]
    return m


TRUTH = LoopTruth(motion)


def yml_text(n):
    """The settings file a Clarius research export writes beside its raw data."""
    return "\n".join([
        "---", "size:", "  number of lines: %d" % LINES, "  samples per line: %d" % n, "  sample size: 2 bytes",
        "type: rf", "compression: none", f"sampling rate: {FS:g} MHz", "delay samples: 0",
        f"transmit frequency: {F0:g} MHz", f"imaging depth: {DEPTH / 10:g} cm", "frame rate: 20 Hz",
        "probe:", f"  elements: {LINES}", f"  pitch: {PITCH * 1e-3:g}", "  radius: 0", ""])


def write(out, name="msk_rf"):
    """Render the loop into ``out``: ``name.raw`` (Clarius raw, int16) and ``name.yml``; returns the raw path."""
    grid = _grid(PROBE, (DEPTH, WIDTH), TOP)
    psf = PROBE.psf()
    hx, hy = psf.half_support_mm()
    x0, x1, y0, y1 = grid.extent()
    pad = 0.5 * COMP[-1] * max(abs(y0), abs(y1)) + SLIDE[-1] + 0.5
    box = (0.0, (1 + COMP[-1] + 0.02) * x1 + hx + 0.5, y0 - hy - pad, y1 + hy + pad + DRIFT.max())
    X, z, amp = elevation_scatterers(PROBE, box, SIG_E, ELEV.max())
    amp[X[:, 0] < SKIN] *= 2.5                                       # bright skin
    amp[(X[:, 0] >= SKIN) & (X[:, 0] < FAT)] *= 0.6                  # hypoechoic fat
    amp[np.abs(X[:, 0] - BAND[0]) < 0.5 * BAND[1]] *= 1.8            # bright fascia
    amp[(X[:, 0] - NOD["xc"]) ** 2 + (X[:, 1] - NOD["yc"]) ** 2 < NOD["R"] ** 2] *= 0.7   # hypoechoic nodule
    gain = 10 ** (attenuation_gain_db(alpha_for_floor(FLOOR, SNR, F0), F0)(grid.x) / 20)
    frames = render_elevation_loop(motion, X, amp, z, ELEV[:N], SIG_E, grid, psf, gain, SNR)
    counts = np.round(frames * (12000.0 / np.abs(frames).max())).astype("<i2")   # int16 counts
    n, ns, nl = counts.shape
    raw = Path(out) / f"{name}.raw"
    with open(raw, "wb") as fh:
        fh.write(np.array([2, n, nl, ns, 2], "<i4").tobytes())         # id, frames, lines, samples, bytes
        for k in range(n):
            fh.write(np.array([1_700_000_000_000_000_000 + k * 50_000_000], "<i8").tobytes())   # ns, 20 Hz
            fh.write(np.ascontiguousarray(counts[k].T).tobytes())      # line after line
    (Path(out) / f"{name}.yml").write_text(yml_text(ns))
    return raw


def errors(path, i, j, lateral0=None):
    """Errors of a femreg result file against the truth of frame i -> j (frame-i coordinates).  ``lateral0``: the
    lateral position (mm) femreg gave the first line (0 without an origin); the truth's 0 is the centre line."""
    import femreg

    res = femreg.load_result(path)
    g = res.on_grid()
    P = res.pixel_points()
    est = np.stack([g["exx"], g["eyy"], g["exy"]], -1).reshape(-1, 3)
    u = np.stack([g["ux"], g["uy"]], -1).reshape(-1, 2)
    P = P + np.array([0.0, -(lateral0 or 0.0) - 0.5 * WIDTH + 0.5 * PITCH])
    ok = (np.all(np.isfinite(est), 1) & (P[:, 0] > 1.0) & (P[:, 0] < 22.0)
          & (np.abs(P[:, 1]) < 0.5 * WIDTH - 1.0))
    if not ok.any():
        return None
    P, est, u = P[ok], est[ok], u[ok]
    t, tu = TRUTH.strain(i, j, P), TRUTH.displacement(i, j, P)
    w = np.array([1.0, 1.0, 2.0])
    # the nodule's centre and the band's depth where frame i images them
    (xc, yc), (xb, _) = motion(i, np.array([[NOD["xc"], NOD["yc"]], [BAND[0], 0.0]]))
    r = np.hypot(P[:, 0] - xc, P[:, 1] - yc)
    inl, bg = r < 1.2, (r > 3.0) & (r < 4.5)
    above, below = np.abs(P[:, 0] - (xb - 2)) < 0.3, np.abs(P[:, 0] - (xb + 2)) < 0.3
    return dict(total=100 * math.sqrt(np.sum(w * (est - t) ** 2) / np.sum(w * t ** 2)),
                exx=100 * math.sqrt(np.sum((est[:, 0] - t[:, 0]) ** 2) / np.sum(t[:, 0] ** 2)),
                ux_um=1e3 * math.sqrt(np.mean((u[:, 0] - tu[:, 0]) ** 2)),
                uy_um=1e3 * math.sqrt(np.mean((u[:, 1] - tu[:, 1]) ** 2)),
                sr=est[bg, 0].mean() / est[inl, 0].mean(), sr_true=t[bg, 0].mean() / t[inl, 0].mean(),
                slide_um=1e3 * (np.median(u[below, 1]) - np.median(u[above, 1])),
                slide_true_um=1e3 * (np.median(tu[below, 1]) - np.median(tu[above, 1])),
                success=bool(res.success), reach_mm=float(P[:, 0].max()))


def say(name, e):
    if e is None:
        print(f"  {name}: nothing registered in the echo")
        return
    print(f"  {name}: total {e['total']:5.1f} %, e_xx {e['exx']:5.1f} %, u RMS {e['ux_um']:.1f} / "
          f"{e['uy_um']:.1f} um, SR {e['sr']:.2f} (true {e['sr_true']:.2f}), slide {e['slide_um']:.1f} um "
          f"(true {e['slide_true_um']:.1f}), success {e['success']}", flush=True)


def femreg_cli(*args, width: int = 220):
    """Run the command as a user does (a fresh process); returns its exit code and prints its wall time and the
    last lines of its output (``width`` characters each)."""
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "femreg", *map(str, args)], capture_output=True, text=True)
    print(f"$ femreg {' '.join(map(str, args))}\n  exit {p.returncode} in {time.perf_counter() - t:.1f} s", flush=True)
    for line in (p.stdout + p.stderr).strip().splitlines()[-8:]:
        print("  | " + line[:width])
    return p.returncode


def walk_args(argv, doc: str, prefix: str):
    """A newcomer walk's command line (an output folder, ``--skip-track``, ``--skip-elastogram``): the parsed
    arguments and the output folder, made (a fresh temporary one named ``prefix...`` when none is given)."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("out", nargs="?")
    ap.add_argument("--skip-track", action="store_true")
    ap.add_argument("--skip-elastogram", action="store_true")
    a = ap.parse_args(argv)
    out = Path(a.out or tempfile.mkdtemp(prefix=prefix))
    out.mkdir(parents=True, exist_ok=True)
    return a, out


def main(argv=None):
    a, out = walk_args(argv, __doc__, "newcomer_msk_")
    t = time.perf_counter()
    raw = write(out)
    print(f"wrote {raw} in {time.perf_counter() - t:.1f} s; compression per frame (%): "
          + " ".join(f"{100 * s:.2f}" for s in STEP))
    sp = ["--spacing", "0.01925", "0.1", "--no-progress"]
    femreg_cli("info", raw)
    femreg_cli("info", raw, *sp)
    femreg_cli("register", raw, "--pair", 2, 3, "-o", out / "swapped.npz", "--spacing", "0.1", "0.01925")
    for i, j in ((2, 3), (14, 15)):
        femreg_cli("register", raw, "--pair", i, j, "-o", out / f"p{i}{j}.npz", *sp)
        if (out / f"p{i}{j}.npz").exists():
            say(f"register {i} -> {j}", errors(out / f"p{i}{j}.npz", i, j))
    for alpha in ("auto", "0.00133"):          # the default alpha smooths the nodule and the slide away
        femreg_cli("register", raw, "--pair", 2, 3, "-o", out / f"p23_{alpha}.npz", "--alpha", alpha, *sp)
        if (out / f"p23_{alpha}.npz").exists():
            say(f"register 2 -> 3 --alpha {alpha}", errors(out / f"p23_{alpha}.npz", 2, 3))
    femreg_cli("register", raw, "--pair", 2, 3, "-o", out / "metres.npz", "--spacing", "0.01925", "0.0001")
    femreg_cli("plot", out / "p23.npz", "--reference", raw, *sp)
    (xc, yc), (xb, _) = motion(2, np.array([[NOD["xc"], NOD["yc"]], [BAND[0], 0.0]]))
    y_file = 0.5 * WIDTH - 0.5 * PITCH           # the file has no origin: its lateral 0 is the first line
    for name in ("p23", "p23_0.00133"):
        femreg_cli("measure", out / f"{name}.npz", "--inclusion", f"{xc:.2f}", f"{yc + y_file:.2f}", 1.2,
                   "--slide", f"{xb - 2:.2f}", f"{xb + 2:.2f}")
    if not a.skip_track:
        femreg_cli("track", raw, "-o", out / "run", "--frames", "0:12", *sp)
        last = out / "run" / "frame_011.npz"
        if last.exists():
            say("track 0 -> 11", errors(last, 0, 11))
            femreg_cli("plot", last, "--reference", raw, *sp)
    if not a.skip_elastogram:
        femreg_cli("elastogram", raw, "-o", out / "loop", *sp)
        if (out / "loop" / "elastogram.npz").exists():
            with np.load(out / "loop" / "elastogram.npz") as d:
                k = int(d["ref_frame"])
            (xc, yc), = motion(k, np.array([[NOD["xc"], NOD["yc"]]]))
            femreg_cli("measure", out / "loop" / "elastogram.npz", "--inclusion", f"{xc:.2f}", f"{yc + y_file:.2f}",
                       1.2)
    print(f"outputs in {out}")


if __name__ == "__main__":
    main()
