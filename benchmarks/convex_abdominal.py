"""A newcomer's recording: an abdominal cine loop of a 3.5 MHz convex probe as a research scanner exports it,
registered from the command line and measured against its exact truth.

Probe C5-2-like: 3.57 MHz, 20.83 MHz sampling (range step c / (2 fs) = 0.03697 mm), apex 49.57 mm behind the
face, 128 rays 0.5 deg apart (63.5 deg), 4096 samples per ray (0-151.4 mm of range, full depth, no crop); the
beam 2.5 rays wide at mid-range (a fixed angle, as forward.beam renders it), 1 mm elevational beam (sigma).
Tissue: liver-like speckle, a stiff lesion (bonded disk, r 10 mm, x4 the background's modulus, 1.4x brighter) at
60 mm depth on the centre line, from a plane-strain FE block (320 mm, the whole top face pressed, bottom fixed;
forward.elasticity.cached_solve) whose top face is the plane 8 mm above the face centre (the fan's sides reach
x = -6.8 mm at range 0).  Attenuation 0.5 dB / (cm MHz) without TGC into a noise floor at about 105 mm (SNR 37 dB
at the face), then a partial TGC (+1.4 dB / cm on echo and noise alike, as a scanner's receive gain), stored as
int16 counts.  7 frames of freehand compression (0.3-1.0 % per frame, 4.2 % in all), 0.05-0.15 mm of lateral
drift and 0.02-0.08 mm of out-of-plane motion per frame.

Written as a Verasonics-style MATLAB v7.3 file: ``RFData(sample, line, frame)`` int16 and a struct ``P`` (fs Hz,
c m/s, f0 Hz, theta: the 128 ray angles in rad, startDepthMm, frameRate Hz, and ``P.Trans``: name, frequency MHz,
radiusMm, numelements).  No ``spacing`` variable: the user passes it.

Prints the wall time of each command and, for ``femreg register --pair 2 3`` (and the other CLI runs), the errors
against the truth over the registered pixels whose range lies within 5-95 mm (the echo): u_x / u_y RMS error (um),
e_xx RMS error relative to the true e_xx's RMS, the total strain error (e_xx, e_yy, 2 e_xy; relative), the lesion's
strain ratio (background ring 1.5-2.5 r over disk within 0.6 r, element-free: the recovered e_xx on the pixels)
and the true one, and the elastogram's normalised-strain error and ratio.

Measured (2026-12-07, 2 shared cores): the echo found to 92.4 mm (pair 2 -> 3) / 99.5 mm (track, elastogram) of
range, where the echo power equals the noise near 94 mm.  register 2 -> 3: 8-17 s, u RMS 1.1 / 2.4 um, e_xx
4.0 %, total 5.1 %, SR 2.50 (true 2.54); track 0 -> 6: 44 s, e_xx 3.9 %, total 4.9 %, u RMS 6.1 / 14.1 um,
SR 2.50 (true 2.52), none flagged (frames 2 and 6 retried from a fresh start); elastogram: 3 of 3 pairs usable,
16 s, normalised-strain error 3.8 %, ratio 2.54 (true 2.57).  Before the beam echo crop and the deep-strip veto
(same data, femreg a5b28b2): the full 151 mm registered, register 2 -> 3 FAILED (peak hopping in the noise, 16 % of
the elements unmatched; e_xx 4.9 % over 5-95 mm), track 6 of 6 frames flagged (93 s), elastogram 0 of 3 pairs
usable (57 s); with the block-matching cut of femreg.echo.unmatched_crop alone the pair registers, its mesh to
115.8 mm of range (21 mm of noise kept, nothing said).
The default alpha of a beam frame is the linear one x ``femreg.geometry.beam_alpha_factor``, whose line spacing
(1.09 mm) is counted in the paper probe's RF periods for this longer pulse (0.215 mm read on the frame; lateral
cell 2.4 lines): 21.4 here, alpha 2.85.  The line spacing alone gave 92 (alpha 12.3): register 2 -> 3 e_xx 5.3 %,
total 6.6 %, SR 2.14; track e_xx 5.0 %, total 6.2 %, u RMS 9.8 / 19.3 um, SR 2.17; elastogram 4.7 %, ratio 2.36.
``--alpha`` 0.133 / 0.4 / 1.2 / 4 gives e_xx 4.4 / 3.7 / 3.7 / 4.3 %, total 5.7 / 4.8 / 4.7 / 5.4 %, SR 2.55 / 2.57
/ 2.57 / 2.46 (pair 2 -> 3); with the factor 92, ``--refine auto`` e_xx 4.5 %, SR 2.42, and NCC block matching
(benchmarks/peers.py, 2 x 3.3 mm windows in (range, arc)): e_rr 11.7 % against femreg's 6.3 % over 5-90 mm and
|theta| < 32 deg, SR 2.42 (femreg 2.06, true 2.45).

Run: ``python benchmarks/convex_abdominal.py [OUTDIR] [--skip-track] [--skip-elastogram]`` (about 3 min).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from forward.fields import LoopTruth  # noqa: E402
from forward.pairs import SCATTERERS_PER_CELL, Probe  # noqa: E402
from forward.ultrasound import ImagingGrid, make_scatterers, noise_sigma, render_rf  # noqa: E402

N = 7                                           # frames
F0, FS, C = 3.57, 20.83, 1540.0                 # MHz, MHz, m/s
DR = C * 1e3 / (2 * FS * 1e6)                   # range step, mm
N_S, N_RAYS = 4096, 128
RADIUS, PITCH_DEG = 49.57, 0.5                  # mm, deg
LINES_PER_BEAM = 2.5
SIG_E = 1.0                                     # elevational beam (sigma), mm
SNR, ALPHA, TGC = 37.0, 0.5, 1.4                # dB at the face; dB/(cm MHz) attenuation; dB/cm receive gain
LES = dict(xc=60.0, yc=0.0, R=10.0)             # stiff lesion (mm)
TOP = 8.0                                       # FE block's top face this far above the face centre, mm
BLOCK = 320.0
_rng = np.random.default_rng(2026)
COMP = np.r_[0.0, np.cumsum(_rng.uniform(0.3, 1.0, N - 1) / 100)]     # compression, fraction
DRIFT = np.r_[0.0, np.cumsum(_rng.uniform(0.05, 0.15, N - 1))]        # probe's lateral drift, mm
ELEV = np.r_[0.0, np.cumsum(_rng.uniform(0.02, 0.08, N - 1))]         # out of plane, mm
PROBE = Probe(F0, FS, 0.3, 1.0, 2.365, name="C5-2-like", c_m_s=C)    # lateral width set per geometry below
RHO_C = RADIUS + 0.5 * (N_S - 1) * DR           # apex distance of the middle sample
DS = RHO_C * math.radians(PITCH_DEG)            # arc spacing of the rays there, mm


def geometry():
    from femreg import Convex

    return Convex(radius_mm=RADIUS, angle_pitch_deg=PITCH_DEG)


class _Field:
    """Displacement per unit compression, (n, 2) mm, on a 0.4 mm grid from the FE solution (cubic spline):
    ``BLOCK (U_FE(x + TOP) - (1, 0))``, so the mean axial strain of the block is -1 and the top face stays put."""

    H = 0.4

    def __init__(self):
        from forward.elasticity import cached_solve

        sol = cached_solve("plane-strain", inclusion_modulus=40.0, background_modulus=10.0, poisson=0.495,
                           block_mm=BLOCK, inclusion_diameter_mm=2 * LES["R"], inclusion_depth_mm=LES["xc"] + TOP,
                           patch_mm=None, compression_mm=1.0, mesh_size_mm=1.0, coarse_size_mm=12.0,
                           refine_region_mm=(175.0, 120.0), bottom="fixed")
        self.x = np.arange(-TOP, 175.0 - TOP + 1e-9, self.H)
        self.y = np.arange(-118.0, 118.0 + 1e-9, self.H)
        X, Y = np.meshgrid(self.x, self.y, indexing="ij")
        u = sol.displacement(np.column_stack([X.ravel() + TOP, Y.ravel()]))
        u[:, 0] -= 1.0
        u *= BLOCK
        if not np.all(np.isfinite(u)):
            raise RuntimeError("FE solution does not cover the imaged region")
        self.coef = [ndimage.spline_filter(u[:, k].reshape(X.shape), order=3) for k in range(2)]

    def __call__(self, p):
        p = np.asarray(p, float)
        idx = np.stack([(p[:, 0] - self.x[0]) / self.H, (p[:, 1] - self.y[0]) / self.H])
        return np.column_stack([ndimage.map_coordinates(c, idx, order=3, prefilter=False, mode="nearest")
                                for c in self.coef])


_U = None


def U(p):
    global _U
    if _U is None:
        _U = _Field()
    return _U(p)


def motion(k, X):
    """Where frame k images the tissue point X (frame-0 physical coordinates, mm)."""
    m = X + COMP[k] * U(X)
    m[:, 1] -= DRIFT[k]
    return m


def true_u(i, j, x):
    """Frame i -> j displacement at frame-i physical points x (n, 2) mm."""
    return LoopTruth(motion).displacement(i, j, x)


def true_strain(i, j, x, h=0.02):
    """Small strain [e_xx, e_yy, e_xy] of frame i -> j at frame-i points (central differences, h mm)."""
    return LoopTruth(motion).strain(i, j, x, h)


def render():
    """The loop, (N, N_S, N_RAYS) float64 RF, and the per-sample gain applied (dB)."""
    geo = geometry()
    grid = ImagingGrid(N_S, N_RAYS, DR, DS, 0.0, -0.5 * (N_RAYS - 1) * DS)
    from dataclasses import replace

    pr = replace(PROBE, beam_fwhm_mm=LINES_PER_BEAM * DS)
    psf = pr.psf()
    hx, hy = psf.half_support_mm()
    Xs, Ys = geo.sample_positions((N_S, N_RAYS), (DR, PITCH_DEG), (0.0, 0.0))
    grow = (RADIUS + N_S * DR) / RHO_C
    m = np.array([0.011 * N_S * DR * COMP[-1] / 0.01 + hx, DRIFT[-1] + hy * grow]) + 1.0
    box = (Xs.min() - m[0], Xs.max() + m[0], Ys.min() - m[1], Ys.max() + m[1])
    rng = np.random.default_rng(7)
    zlo, zhi = -3 * SIG_E, ELEV.max() + 3 * SIG_E
    # physical density so that the beam grid (range, arc at RHO_C) holds SCATTERERS_PER_CELL per cell at RHO_C;
    # deeper the physical fan widens (sparser on the grid), shallower it narrows: as forward.beam
    dens = pr.density_per_mm2(SCATTERERS_PER_CELL) * (zhi - zlo) / (math.sqrt(2 * math.pi) * SIG_E)
    scat = make_scatterers(rng, box, density_per_mm2=dens * 2.0, inclusion_radius_mm=None,
                           cell_aspect=psf.sigma_axial_mm / psf.sigma_lateral_mm)
    X = scat.positions
    r0, th0 = geo.to_beam(X[:, 0], X[:, 1])
    keep = (X[:, 0] >= -TOP) & (r0 > -3 * hx) & (r0 < N_S * DR + m[0]) & (np.abs(th0) < math.radians(
        0.5 * N_RAYS * PITCH_DEG) + (hy * grow + m[1]) / (RADIUS + np.maximum(r0, 1.0)))
    X, amp = X[keep], scat.amplitudes[keep]
    z = rng.uniform(zlo, zhi, len(X))
    amp = amp * np.where((X[:, 0] - LES["xc"]) ** 2 + (X[:, 1] - LES["yc"]) ** 2 < LES["R"] ** 2, 1.4, 1.0)
    depth = Xs.mean(axis=1)                                          # along the centre ray ~ range
    r_axis = np.arange(N_S) * DR
    gain_db = -2 * ALPHA * F0 * r_axis / 10.0                        # round trip, range in mm -> dB
    tgc_db = TGC * r_axis / 10.0
    frames = np.empty((N, N_S, N_RAYS))
    nrng = np.random.default_rng(11)
    sigma = 0.0
    for k in range(N):
        w = np.exp(-0.5 * ((z - ELEV[k]) / SIG_E) ** 2)
        on = w > 1e-3
        q = motion(k, X[on])
        r, th = geo.to_beam(q[:, 0], q[:, 1])
        clean = render_rf(np.column_stack([r, RHO_C * th]), amp[on] * w[on], grid, psf)
        if k == 0:
            sigma = noise_sigma(float(np.mean(clean[: N_S // 8] ** 2)), SNR)
        rf = clean * 10 ** (gain_db / 20)[:, None] + sigma * nrng.standard_normal(clean.shape)
        frames[k] = rf * 10 ** (tgc_db / 20)[:, None]
    del depth
    return frames, gain_db + tgc_db


def write(out):
    """Render the loop into ``out/abdomen.mat`` (MATLAB v7.3, Verasonics-style) and return its path."""
    import h5py

    frames, _ = render()
    scale = 6000.0 / np.percentile(np.abs(frames), 99.99)           # a 14-bit ADC's counts, never clipped
    counts = np.clip(np.round(frames * scale), -32767, 32767).astype(np.int16)
    path = out / "abdomen.mat"
    theta = (np.arange(N_RAYS) - 0.5 * (N_RAYS - 1)) * math.radians(PITCH_DEG)
    with h5py.File(path, "w", userblock_size=512) as f:
        # RFData(sample, line, frame) in MATLAB: HDF5 holds the transpose (frame, line, sample)
        ds = f.create_dataset("RFData", data=np.ascontiguousarray(counts.transpose(0, 2, 1)))
        ds.attrs["MATLAB_class"] = np.bytes_("int16")
        g = f.create_group("P")
        g.attrs["MATLAB_class"] = np.bytes_("struct")

        def num(grp, name, v):
            d = grp.create_dataset(name, data=np.atleast_2d(np.asarray(v, float)).T)
            d.attrs["MATLAB_class"] = np.bytes_("double")

        def text(grp, name, s):
            d = grp.create_dataset(name, data=np.array([[ord(ch)] for ch in s], np.uint16))
            d.attrs["MATLAB_class"] = np.bytes_("char")

        num(g, "fs", FS * 1e6)
        num(g, "c", C)
        num(g, "f0", F0 * 1e6)
        num(g, "theta", theta[None, :])
        num(g, "startDepthMm", 0.0)
        num(g, "frameRate", 25.0)
        t = g.create_group("Trans")
        t.attrs["MATLAB_class"] = np.bytes_("struct")
        text(t, "name", "C5-2v")
        num(t, "frequency", F0)
        num(t, "radiusMm", RADIUS)
        num(t, "numelements", 128)
    stamp = time.strftime("%a %b %d %H:%M:%S %Y", time.gmtime())
    head = f"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: {stamp} HDF5 schema 1.00 .".encode("ascii")
    with open(path, "r+b") as fh:
        fh.write((head.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM").ljust(512, b"\x00"))
    return path


def _points(res):
    """(physical points (n, 2), ranges (n,)) of a result's pixel grid (a beam result's samples)."""
    P = np.asarray(res.pixel_points(), float)
    r, _ = geometry().to_beam(P[:, 0], P[:, 1])
    return P, r


def errors(path, i, j):
    """Errors of a femreg result file against the truth of frame i -> j over registered samples at 5-95 mm."""
    import femreg

    res = femreg.load_result(path)
    g = res.on_grid()
    P, r = _points(res)
    est = np.stack([g["exx"], g["eyy"], g["exy"]], -1).reshape(-1, 3)
    u = np.stack([g["ux"], g["uy"]], -1).reshape(-1, 2)
    ok = np.all(np.isfinite(est), 1) & np.all(np.isfinite(u), 1) & (r > 5.0) & (r < 95.0)
    cover = float(np.mean(np.all(np.isfinite(est), 1)[(r > 5.0) & (r < 95.0)]))
    P, est, u = P[ok], est[ok], u[ok]
    t, tu = true_strain(i, j, P), true_u(i, j, P)
    w = np.array([1.0, 1.0, 2.0])
    tot = 100 * math.sqrt(np.sum(w * (est - t) ** 2) / np.sum(w * t ** 2))
    d = np.hypot(P[:, 0] - LES["xc"], P[:, 1] - LES["yc"])
    inl, bg = d < 0.6 * LES["R"], (d > 1.5 * LES["R"]) & (d < 2.5 * LES["R"])
    return dict(total=tot, exx=100 * math.sqrt(np.sum((est[:, 0] - t[:, 0]) ** 2) / np.sum(t[:, 0] ** 2)),
                ux_um=1e3 * math.sqrt(np.mean((u[:, 0] - tu[:, 0]) ** 2)),
                uy_um=1e3 * math.sqrt(np.mean((u[:, 1] - tu[:, 1]) ** 2)),
                sr=est[bg, 0].mean() / est[inl, 0].mean(), sr_true=t[bg, 0].mean() / t[inl, 0].mean(),
                exx_mean=100 * est[:, 0].mean(), exx_true=100 * t[:, 0].mean(), cover=100 * cover,
                success=bool(res.success))


def elastogram_errors(folder):
    """Normalised-strain error (%) and disk ratio of ``femreg elastogram``'s elastogram.npz against the truth of
    its reference frame's pair (as benchmarks/elastogram_convex.py)."""
    z = np.load(folder / "elastogram.npz", allow_pickle=False)
    e = np.asarray(z["exx"], float)
    x = np.asarray(z["x"], float) if "x" in z.files else z["origin"][0] + z["spacing"][0] * np.arange(e.shape[0])
    y = np.asarray(z["y"], float) if "y" in z.files else z["origin"][1] + z["spacing"][1] * np.arange(e.shape[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])
    ref = int(z["ref_frame"]) if "ref_frame" in z.files else 0
    pairs = [tuple(p) for p in np.asarray(z["pairs"]).tolist()] if "pairs" in z.files else [(ref, ref + 1)]
    i, j = pairs[0]
    ok = np.isfinite(e.ravel())
    r, _ = geometry().to_beam(pts[:, 0], pts[:, 1])
    ok &= (r > 5.0) & (r < 95.0)
    t = np.full(len(pts), np.nan)
    t[ok] = true_strain(i, j, pts[ok])[:, 0]
    en, tn = e.ravel() / np.mean(e.ravel()[ok]), t / np.mean(t[ok])
    err = 100 * float(np.sqrt(np.mean((en[ok] - tn[ok]) ** 2)))
    d = np.hypot(pts[:, 0] - LES["xc"], pts[:, 1] - LES["yc"])
    disk, ring = ok & (d < 0.6 * LES["R"]), ok & (d > 1.5 * LES["R"]) & (d < 2.5 * LES["R"])
    return dict(err=err, ratio=float(en[ring].mean() / en[disk].mean()),
                ratio_true=float(tn[ring].mean() / tn[disk].mean()), pair=(i, j))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?")
    ap.add_argument("--skip-track", action="store_true")
    ap.add_argument("--skip-elastogram", action="store_true")
    a = ap.parse_args(argv)
    from femreg.cli import main as femreg

    out = Path(a.out or tempfile.mkdtemp(prefix="convex_abdominal_"))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scan = str(write(out))
    print(f"wrote {scan} ({N} frames, {N_S} x {N_RAYS}, int16) in {time.perf_counter() - t0:.0f} s; compression "
          f"per frame {', '.join(f'{100 * d:.2f}' for d in np.diff(COMP))} %", flush=True)
    geo = ["--geometry", "convex", "--radius", f"{RADIUS:g}", "--angle-pitch", f"{PITCH_DEG:g}",
           "--spacing", f"{DR:.6g}", "auto", "--no-progress"]
    rows = []
    t = time.perf_counter()
    rc = femreg(["register", scan, "--pair", "2", "3", "-o", str(out / "p23.npz")] + geo)
    rows.append(("register 2 -> 3", rc, time.perf_counter() - t, errors(out / "p23.npz", 2, 3)))
    if not a.skip_track:
        t = time.perf_counter()
        rc = femreg(["track", scan, "-o", str(out / "track")] + geo)
        rows.append((f"track 0 -> {N - 1}", rc, time.perf_counter() - t,
                     errors(out / "track" / f"frame_{N - 1:03d}.npz", 0, N - 1)))
    for name, rc, wall, e in rows:
        print(f"{name:18s} exit {rc}  {wall:5.1f} s  covered {e['cover']:.0f} %  u RMS {e['ux_um']:.1f} / "
              f"{e['uy_um']:.1f} um  e_xx {e['exx']:.1f} %  total {e['total']:.1f} %  mean e_xx {e['exx_mean']:.3f} "
              f"(true {e['exx_true']:.3f}) %  SR {e['sr']:.2f} (true {e['sr_true']:.2f})  success {e['success']}",
              flush=True)
    if not a.skip_elastogram:
        t = time.perf_counter()
        rc = femreg(["elastogram", scan, "-o", str(out / "loop"), "--band", "0.5", "2"] + geo)
        wall = time.perf_counter() - t
        try:
            e = elastogram_errors(out / "loop")
            print(f"elastogram         exit {rc}  {wall:5.1f} s  pair {e['pair']}  normalised-strain error "
                  f"{e['err']:.1f} %  ratio {e['ratio']:.2f} (true {e['ratio_true']:.2f})")
        except (OSError, KeyError) as exc:
            print(f"elastogram         exit {rc}  {wall:5.1f} s  not scored: {exc}")
    (out / "truth.json").write_text(json.dumps(dict(comp=COMP.tolist(), drift=DRIFT.tolist(), elev=ELEV.tolist(),
                                                    lesion=LES, dr=DR, radius=RADIUS, pitch_deg=PITCH_DEG)))


if __name__ == "__main__":
    main()
