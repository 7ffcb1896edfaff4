"""Cross-check of forward.volume's separable 3D PSF against pymust's SIMUS3 (matrix-array simulator, Garcia's MUST).

SIMUS3 side: a 7 MHz planar matrix array (32 x 16 elements, 0.2 mm pitch: 6.4 mm lateral x 3.2 mm elevational
aperture), 60 % pulse-echo bandwidth, transmit and receive focused at 20 mm (fixed focus, delay-and-sum of the
element signals with the transmit delays as receive delays).  A scan line is one transmit/receive on the array
axis; other lines are the scatterers shifted by the line's offset (a translation-invariant scan).

1. Point response: one scatterer at lateral / elevational offsets around the axis at the focal depth (20 mm) and
   off focus (12 mm) -> envelope peak vs offset -> lateral and elevational FWHM; the on-axis envelope in depth ->
   axial FWHM.
2. forward.volume's PSF with the SIMUS3 focal widths and the pulse of the same bandwidth (Gaussian envelope:
   time FWHM = 4 ln 2 / (pi B f0)) and the Gaussian-beam widening of its docstring predicts the off-focus widths
   and the axial FWHM: compared with SIMUS3's.
3. Speckle: the same stratified scatterers (forward.volume.make_scatterers_3d) rendered by both on a grid of
   lines around the focus: envelope mean/std (Rayleigh 1.91), axial speckle size (envelope autocorrelation
   FWHM), and the correlation of the two simulators' envelopes line by line (the same scatterers: a matched PSF
   gives a high correlation).

SIMUS3 outputs are cached under ``forward.elasticity.cache_dir() / "pymust"`` (not in git).  Without pymust
(``pip install femreg[bench]``) the script says so and exits 0.

Run: ``python benchmarks/psf3d_crosscheck.py [--lines N]`` (N x N speckle lines, default 2; SIMUS3 takes about
1-2 min of one core per line of 4.5 k scatterers, so the speckle part is small on 2 cores).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from femreg.speckle import envelope  # noqa: E402
from forward.volume import PSF3D, ImagingVolume, make_scatterers_3d, render_volume  # noqa: E402

C = 1540.0
FC = 7e6
BW = 0.60
NX, NY, PITCH = 32, 16, 0.2e-3
ZF = 20e-3


def _param(pymust):
    from pymust import utils

    p = utils.Param()
    p.fc, p.bandwidth, p.c, p.fs = FC, 100 * BW, C, 8 * FC
    ex = (np.arange(NX) - (NX - 1) / 2) * PITCH
    ey = (np.arange(NY) - (NY - 1) / 2) * PITCH
    EX, EY = np.meshgrid(ex, ey, indexing="ij")
    p.elements = np.vstack([EX.ravel(), EY.ravel()])
    p.width = p.height = 0.9 * PITCH
    dist = np.sqrt(EX.ravel() ** 2 + EY.ravel() ** 2 + ZF ** 2)
    delays = ((dist.max() - dist) / C)[None, :]        # focus at (0, 0, ZF); pymust's txdelay3 needs a 1D array
    p.RXdelay = delays.copy()
    return p, delays


def _line(pymust, xs, ys, zs, rc):
    """Beamformed RF line (sum of the receive-delayed element signals) of scatterers at (xs lateral, ys
    elevational, zs depth) m, and its sampling frequency."""
    p, d = _param(pymust)
    rf, _ = pymust.simus3(np.asarray(xs, float), np.asarray(ys, float), np.asarray(zs, float),
                          np.asarray(rc, float), d, p)
    return np.asarray(rf, float).sum(axis=1), p.fs


def _cache(name, fn):
    from forward.elasticity import cache_dir

    folder = cache_dir() / "pymust"
    folder.mkdir(parents=True, exist_ok=True)
    key = hashlib.sha256(json.dumps([name, FC, BW, NX, NY, PITCH, ZF, 2]).encode()).hexdigest()[:12]
    path = folder / f"{name.split('(')[0]}_{key}.npz"
    if path.is_file():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    out = fn()
    np.savez(path, **out)
    return out


def fwhm(profile, step):
    p = np.asarray(profile, float)
    p = p / p.max()
    above = np.flatnonzero(p >= 0.5)
    lo, hi = above[0], above[-1]
    left = lo - (p[lo] - 0.5) / (p[lo] - p[lo - 1]) if lo > 0 else lo
    right = hi + (p[hi] - 0.5) / (p[hi] - p[hi + 1]) if hi < len(p) - 1 else hi
    return float((right - left) * step)


def simus_point(pymust, depth_mm):
    offs_lat = np.linspace(-3.0, 3.0, 61)
    offs_el = np.linspace(-5.0, 5.0, 51)

    def run():
        z = depth_mm * 1e-3
        lat = [np.abs(envelope(_line(pymust, [o * 1e-3], [0.0], [z], [1.0])[0][:, None])).max() for o in offs_lat]
        el = [np.abs(envelope(_line(pymust, [0.0], [o * 1e-3], [z], [1.0])[0][:, None])).max() for o in offs_el]
        line, fs = _line(pymust, [0.0], [0.0], [z], [1.0])
        return dict(lat=np.array(lat), el=np.array(el), axial=line, fs=np.array(fs))

    r = _cache(f"point{depth_mm:g}", run)
    ax_env = envelope(r["axial"][:, None])[:, 0]
    return dict(lateral=fwhm(r["lat"], offs_lat[1] - offs_lat[0]),
                elevational=fwhm(r["el"], offs_el[1] - offs_el[0]),
                axial=fwhm(ax_env, C * 1e3 / (2 * float(r["fs"]))))


def model_psf(lat_focus_mm, el_focus_mm):
    t6 = 4 * math.log(2) / (math.pi * BW * FC)      # Gaussian envelope: time FWHM x amplitude-spectrum FWHM
    return PSF3D(FC, t6, lat_focus_mm, el_focus_mm, lateral_focus_mm=ZF * 1e3, elevational_focus_mm=ZF * 1e3)


def model_point(psf, depth_mm):
    g = ImagingVolume((240, 121, 101), (C * 1e3 / (2 * 8 * FC), 0.05, 0.1), (depth_mm - 2.0, -3.0, -5.0))
    R = render_volume(np.array([[depth_mm, 0.0, 0.0]]), np.ones(1), g, psf, dtype=np.float64)
    env = envelope(R.reshape(R.shape[0], -1)).reshape(R.shape)
    i, j, k = np.unravel_index(np.argmax(env), env.shape)
    return dict(axial=fwhm(env[:, j, k], g.spacing[0]), lateral=fwhm(env[i, :, k], 0.05),
                elevational=fwhm(env[i, j, :], 0.1))


def speckle(pymust, psf, n_lines):
    """SIMUS3 and model lines over the same scatterers (lines within 0.6 mm laterally and 1.0 mm elevationally of the axis, around the focus)."""
    rng = np.random.default_rng(7)
    box = (18.8, 21.2, -1.8, 1.8, -2.8, 2.8)              # depth, lateral, elevational mm: lines + beam
    dens = 1.0 / (psf.sigma_axial_mm * float(psf.sigma_lateral_mm()) * float(psf.sigma_elevational_mm()))
    sig = [psf.sigma_axial_mm, float(psf.sigma_lateral_mm()), float(psf.sigma_elevational_mm())]
    sc = make_scatterers_3d(rng, box, density_per_mm3=dens, cell_aspect=sig)
    offs = [(a, b) for a in np.linspace(-0.6, 0.6, n_lines) for b in np.linspace(-1.0, 1.0, n_lines)]

    def one(a, b):             # one cache file per line: a long run keeps what it has done
        x, y, z = sc.positions[:, 1] - a, sc.positions[:, 2] - b, sc.positions[:, 0]
        return lambda: dict(line=_line(pymust, x * 1e-3, y * 1e-3, z * 1e-3, sc.amplitudes)[0])

    t0 = time.perf_counter()
    lines = [_cache(f"speckle{len(sc)}_{a:+.3f}_{b:+.3f}", one(a, b))["line"] for a, b in offs]
    n = min(len(v) for v in lines)
    sim = np.array([v[:n] for v in lines])
    t_sim = time.perf_counter() - t0
    # depth of SIMUS3 samples: the on-axis point at the focus marks ZF (pulse and delays fixed)
    ref, fs = _line(pymust, [0.0], [0.0], [ZF], [1.0])
    t_peak = int(np.argmax(envelope(ref[:, None])[:, 0]))
    dx = C * 1e3 / (2 * fs)
    depth = ZF * 1e3 + (np.arange(sim.shape[1]) - t_peak) * dx
    win = (depth > 19.5) & (depth < 20.5)
    g = ImagingVolume((int(win.sum()), 1, 1), (dx, 1.0, 1.0), (float(depth[win][0]), 0.0, 0.0))
    t0 = time.perf_counter()
    mod = np.array([render_volume(sc.positions - [0.0, a, b], sc.amplitudes, g, psf, dtype=np.float64)[:, 0, 0]
                    for a, b in offs])
    t_mod = time.perf_counter() - t0
    e_sim = envelope(sim[:, win].T).T
    e_mod = envelope(mod.T).T

    def stats(e):
        r = float(e.mean() / e.std())
        a = e - e.mean(axis=1, keepdims=True)
        ac = np.mean([np.correlate(v, v, "full")[len(v) - 1:] / np.dot(v, v) for v in a], axis=0)
        below = np.flatnonzero(ac < 0.5)
        return r, 2.0 * (below[0] if below.size else len(ac)) * dx

    rs, ss = stats(e_sim)
    rm, sm = stats(e_mod)
    corr = float(np.mean([np.corrcoef(a, b)[0, 1] for a, b in zip(e_sim, e_mod)]))
    return dict(n_scatterers=len(sc), n_lines=len(offs), snr_env_simus=rs, snr_env_model=rm,
                speckle_axial_simus=ss, speckle_axial_model=sm, envelope_correlation=corr, time_simus_s=t_sim,
                time_model_s=t_mod)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lines", type=int, default=2)
    args = ap.parse_args(argv)
    try:
        import pymust
    except ImportError:
        print("pymust is not installed (pip install femreg[bench]): no SIMUS3 cross-check")
        return 0
    t0 = time.perf_counter()
    focus = simus_point(pymust, 20.0)
    off = simus_point(pymust, 12.0)
    print(f"SIMUS3 point responses: {time.perf_counter() - t0:.1f} s (cached after the first run)")
    psf = model_psf(focus["lateral"], focus["elevational"])
    m_focus, m_off = model_point(psf, 20.0), model_point(psf, 12.0)
    print("\npulse-echo FWHM, mm            SIMUS3   model")
    for name, s, m in (("axial (focus 20 mm)", focus["axial"], m_focus["axial"]),
                       ("lateral (focus, matched)", focus["lateral"], m_focus["lateral"]),
                       ("elevational (focus, matched)", focus["elevational"], m_focus["elevational"]),
                       ("axial (12 mm)", off["axial"], m_off["axial"]),
                       ("lateral (12 mm)", off["lateral"], m_off["lateral"]),
                       ("elevational (12 mm)", off["elevational"], m_off["elevational"])):
        print(f"  {name:30s} {s:6.3f}  {m:6.3f}   ({100 * (m - s) / s:+.0f} %)")
    sp = speckle(pymust, psf, args.lines)
    print(f"\nspeckle ({sp['n_scatterers']} scatterers, {sp['n_lines']} lines, depth 19.5-20.5 mm):")
    print(f"  envelope mean/std          SIMUS3 {sp['snr_env_simus']:.2f}  model {sp['snr_env_model']:.2f}  "
          "(Rayleigh 1.91)")
    print(f"  axial speckle size (mm)    SIMUS3 {sp['speckle_axial_simus']:.3f}  model "
          f"{sp['speckle_axial_model']:.3f}")
    print(f"  envelope correlation line by line (same scatterers): {sp['envelope_correlation']:.2f}")
    print(f"  time: SIMUS3 {sp['time_simus_s']:.1f} s (or cache), model {sp['time_model_s']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
