"""The paper's simulated RF image sequences: compression schedule, rendering of the frames, true fields, save/load.

One forward solve per model (linear elasticity scales with the load): the FE displacement ``U(X)`` for a unit
compression of the patch (1 mm) is evaluated **once at the scatterer positions themselves**, and frame ``k``
renders the same scatterers at ``X + s_k U(X)`` (:mod:`forward.ultrasound`).  The scale factors ``s_k`` are set
so that the mean axial compressive strain over the imaged area follows :func:`paper_schedule`.

True fields (frame 0 -> frame k, frame-0 coordinates, the registration convention ``I_0(x) ~ I_k(x + u(x))``):
``u_k(x) = s_k U(x)``, ``eps_k(x) = s_k E(x)``.  ``U`` and the strain ``E = [exx, eyy, exy]`` are sampled from the
forward model on a regular 0.1 mm grid covering the imaged area plus 1 mm, stored in the sequence file, and
interpolated bilinearly (:meth:`Sequence.true_displacement`, :meth:`Sequence.true_strain`).  Live and reloaded
sequences use that same stored grid, so the true fields are bit-identical after :func:`load_sequence`, and they
need neither the FE mesh nor a re-solve.  (Bilinear interpolation of a 0.1 mm sampling differs from the FE field
by ``O(h^2 |grad^2 u|)`` ~ 1e-6 mm in smooth parts and smears the strain jump at the inclusion interface over 0.1 mm.)

Imaging geometry: the probe is fixed in the forward model's coordinates (the paper's frame); tissue exists only
below the top face ``x = 0``, so as the surface moves down, the top band ``0 <= x < u_x(0)`` of later frames is
echo-free (noise only).  Frame-0 points always map into tissue, so the registration domain (frame-0 coordinates)
never sees that band.  Scatterers fill the imaged area plus a margin (the largest displacement reached in the
sequence plus the PSF support plus 0.5 mm) on the sides and bottom, so no tissue enters the field of view empty.
"""
from __future__ import annotations

import hashlib
import inspect
import json
import math
import time
from dataclasses import dataclass, field as dc_field
from pathlib import Path

import numpy as np
import scipy.ndimage
from femreg.io import atomic_savez

from .ultrasound import PSF, ImagingGrid, add_noise, make_scatterers, noise_sigma, render_rf

__all__ = [
    "MODELS", "INCLUSIONS", "BACKGROUND_MODULUS", "PAPER_DATASETS", "FORMAT_VERSION",
    "paper_schedule", "AnalyticField", "Sequence", "simulate_sequence", "load_sequence", "get_sequence",
    "paper_datasets", "dataset_name", "parse_dataset_name", "schedule_figures", "sequence_cache_dir",
]

#: Forward model names (issue 2's ``forward.solve_elasticity(model=...)``).
MODELS = ("3d", "plane-strain", "plane-stress")
#: Inclusion names -> Young's modulus, MPa (paper: HI 40, mHI 20, HOM 10, SI 5).
INCLUSIONS = {"HI": 40.0, "mHI": 20.0, "HOM": 10.0, "SI": 5.0}
#: Background Young's modulus, MPa.
BACKGROUND_MODULUS = 10.0
#: The paper's six data sets, (model, inclusion).
PAPER_DATASETS = (("3d", "HI"), ("3d", "mHI"), ("3d", "HOM"), ("3d", "SI"), ("plane-strain", "HI"),
                  ("plane-stress", "HI"))
#: Bump when the file layout or anything that changes the generated frames changes (invalidates caches).
FORMAT_VERSION = 1

_TOL_OUTSIDE_MM = 0.5  # points this close outside the stored field box are clamped onto it


def dataset_name(model: str, inclusion: str) -> str:
    """``"3d-HI"``, ``"plane-strain-HI"``, ... (the CLI's and :func:`paper_datasets`' keys)."""
    return f"{_check_model(model)}-{_check_inclusion(inclusion)}"


def parse_dataset_name(name: str) -> tuple[str, str]:
    """Inverse of :func:`dataset_name`; ValueError naming ``name`` if it is not one."""
    model, _, inc = str(name).rpartition("-")
    if model not in MODELS or inc not in INCLUSIONS:
        valid = ", ".join(dataset_name(m, i) for m, i in PAPER_DATASETS)
        raise ValueError(f"unknown data set {name!r}: expected <model>-<inclusion> with model in {MODELS} and "
                         f"inclusion in {tuple(INCLUSIONS)} (paper: {valid})")
    return model, inc


def _check_model(model) -> str:
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}: expected one of {MODELS}")
    return model


def _check_inclusion(inclusion) -> str:
    if inclusion not in INCLUSIONS:
        raise ValueError(f"unknown inclusion {inclusion!r}: expected one of {tuple(INCLUSIONS)}")
    return inclusion


# --------------------------------------------------------------------------------------------------------------
# Compression schedule
# --------------------------------------------------------------------------------------------------------------

def paper_schedule(n_frames: int = 20, *, total: float = 0.07, early: float = 0.008, early_steps: int = 6,
                   max_step: float = 0.008) -> np.ndarray:
    """Cumulative mean axial compressive strain (fraction, >= 0) of each frame relative to frame 0.

    The paper's schedule (20 frames; frame 1 of the paper is index 0): the first ``early_steps`` = 6 increments
    share ``early`` = 0.8 % equally (frames 1 -> 7 about 0.8 %, the alpha-selection pair), then the increments
    grow linearly up to ``max_step`` = 0.8 % at the last step so that frame 20 reaches ``total`` = 7 %.  Mean
    step 7 % / 19 = 0.37 %, maximum 0.8 %.  Fewer frames take the first ``n_frames`` of this schedule; more frames
    continue at ``max_step`` per frame.

    Returns
    -------
    (n_frames,) float, ``[0, ...]``.
    """
    n_frames = _check_n_frames(n_frames)
    n_paper = 20
    late = n_paper - 1 - early_steps
    first_late = 2.0 * (total - early) / late - max_step  # linear ramp first_late -> max_step sums to total-early
    steps = np.concatenate([np.full(early_steps, early / early_steps), np.linspace(first_late, max_step, late)])
    if n_frames > n_paper:
        steps = np.concatenate([steps, np.full(n_frames - n_paper, max_step)])
    return np.concatenate([[0.0], np.cumsum(steps)])[:n_frames]


def _check_n_frames(n_frames) -> int:
    if isinstance(n_frames, bool) or int(n_frames) != n_frames or int(n_frames) < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    return int(n_frames)


# --------------------------------------------------------------------------------------------------------------
# Displacement fields
# --------------------------------------------------------------------------------------------------------------

class AnalyticField:
    """Smooth closed-form stand-in for a forward solution at 1 mm compression (tests, benchmarks, no FE needed).

    ``u_x = (H - x)/H - beta (x - x_c) g / H``, ``u_y = y / (2 H)``, ``g = exp(-r^2 / (2 R^2))`` with ``r`` the
    distance to the inclusion centre ``(x_c, y_c)``, ``R`` its radius and ``beta = sqrt(E_b / E_i) - 1``: uniform
    compression ``-1/H`` (``H`` = block height, bottom fixed) plus a Gaussian bump that lowers the axial strain in a
    hard inclusion and raises it in a soft one.  Same interface as the FE ``Solution``: ``displacement(points)``
    -> (n, 2) mm, ``strain(points)`` -> (n, 3) [exx, eyy, exy], NaN outside the block ``0 <= x <= H``,
    ``|y| <= H/2`` (like the FE solution's default).  Not a solution of elasticity.
    """

    def __init__(self, inclusion_modulus: float = 40.0, background_modulus: float = BACKGROUND_MODULUS, *,
                 block_mm: float = 160.0, inclusion_depth_mm: float = 30.0, inclusion_diameter_mm: float = 15.0):
        self.H = float(block_mm)
        self.xc, self.yc = float(inclusion_depth_mm), 0.0
        self.R = float(inclusion_diameter_mm) / 2.0
        self.beta = math.sqrt(float(background_modulus) / float(inclusion_modulus)) - 1.0

    def _parts(self, points):
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must be (n, 2) [x, y] mm, got shape {p.shape}")
        dx, dy = p[:, 0] - self.xc, p[:, 1] - self.yc
        g = np.exp(-(dx**2 + dy**2) / (2 * self.R**2))
        outside = (p[:, 0] < 0) | (p[:, 0] > self.H) | (np.abs(p[:, 1]) > self.H / 2)
        g[outside] = np.nan
        return p, dx, dy, g

    def displacement(self, points) -> np.ndarray:
        p, dx, _, g = self._parts(points)
        ux = (self.H - p[:, 0]) / self.H - self.beta * dx * g / self.H
        uy = p[:, 1] / (2 * self.H) + 0 * g  # NaN outside, like ux
        return np.column_stack([ux, uy])

    def strain(self, points) -> np.ndarray:
        p, dx, dy, g = self._parts(points)
        exx = -1.0 / self.H - self.beta * g * (1.0 - dx**2 / self.R**2) / self.H
        eyy = 0.5 / self.H + 0 * g
        dux_dy = self.beta * dx * dy * g / (self.H * self.R**2)
        return np.column_stack([exx, eyy, 0.5 * dux_dy])


def _fe_kwargs(model, inclusion_modulus, background_modulus, inclusion_depth_mm, inclusion_diameter_mm,
               fe_options) -> dict:
    return dict(model=model, inclusion_modulus=float(inclusion_modulus),
                background_modulus=float(background_modulus), inclusion_depth_mm=float(inclusion_depth_mm),
                inclusion_diameter_mm=float(inclusion_diameter_mm), compression_mm=1.0, **dict(fe_options or {}))


def _fe_cache_key(model, **kw) -> str | None:
    """The forward model's own cache key of the solve :func:`_fe_field` makes (captures its mesh defaults and
    version), or None when the FE module is not available."""
    try:
        from .elasticity import cache_key
    except ImportError:
        return None
    kwargs = _fe_kwargs(model, **kw)
    kwargs.pop("model")
    return cache_key(model, **kwargs)


def _fe_field(model: str, inclusion_modulus: float, background_modulus: float, inclusion_depth_mm: float,
              inclusion_diameter_mm: float, fe_options: dict):
    """The one place that calls the FE forward model (issue 2): a solution at 1 mm patch compression, through
    ``forward.cached_solve`` (disk cache keyed by every solve parameter).  Returns ``(solution, source)``."""
    from .elasticity import cached_solve

    kwargs = _fe_kwargs(model, inclusion_modulus, background_modulus, inclusion_depth_mm, inclusion_diameter_mm,
                        fe_options)
    return cached_solve(**kwargs), "fe:cached_solve"


def _eval_field(field, points: np.ndarray, chunk: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """(displacement (n, 2), strain (n, 3)) of ``field`` at ``points``, chunked; non-finite -> ValueError."""
    u = np.empty((len(points), 2))
    e = np.empty((len(points), 3))
    for a in range(0, len(points), chunk):
        u[a:a + chunk] = field.displacement(points[a:a + chunk])
        e[a:a + chunk] = field.strain(points[a:a + chunk])
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(e))):
        raise ValueError("the forward field returned non-finite values inside the imaged area")
    return u, e


def _eval_displacement(field, points: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    u = np.empty((len(points), 2))
    for a in range(0, len(points), chunk):
        u[a:a + chunk] = field.displacement(points[a:a + chunk])
    if not np.all(np.isfinite(u)):
        raise ValueError("the forward field returned non-finite displacements at scatterer positions")
    return u


# --------------------------------------------------------------------------------------------------------------
# Sequence
# --------------------------------------------------------------------------------------------------------------

@dataclass
class Sequence:
    """A simulated RF sequence with its true motion.

    Attributes
    ----------
    frames : (n_frames, n_axial, n_lateral) float32
        RF frames; frame 0 is the undeformed reference.
    grid : ImagingGrid
        Pixel grid; ``spacing = (dx, dy)`` mm and ``origin = (x, y)`` mm of pixel [0, 0]'s centre in the forward
        model's imaging-plane coordinates (x depth below the top face, y lateral from the centre line).
    scales : (n_frames,) float
        Patch compression of each frame in units of the stored unit (1 mm) field.
    field_x, field_y : 1-D float
        Axial/lateral coordinates (mm) of the regular grid the unit fields are sampled on.
    unit_displacement : (len(field_x), len(field_y), 2) float
        [ux, uy] of the forward model at 1 mm compression, mm.
    unit_strain : (len(field_x), len(field_y), 3) float
        [exx, eyy, exy] at 1 mm compression.
    inclusion_mask : (n_axial, n_lateral) bool
        Pixels whose centre lies inside the inclusion (frame 0): the ROI for SR and CNR_e.
    params : dict
        Every parameter, the seed and provenance (JSON-serialisable).
    """

    frames: np.ndarray
    grid: ImagingGrid
    scales: np.ndarray
    field_x: np.ndarray
    field_y: np.ndarray
    unit_displacement: np.ndarray
    unit_strain: np.ndarray
    inclusion_mask: np.ndarray
    params: dict = dc_field(default_factory=dict)
    path: Path | None = None

    def __repr__(self) -> str:
        p = self.params
        return (f"Sequence({p.get('model')}/{p.get('inclusion')}, frames {tuple(self.frames.shape)}, spacing "
                f"{self.spacing} mm, origin {self.origin} mm, seed {p.get('seed')}, snr_db {p.get('snr_db')}, "
                f"field {p.get('field_source')})")

    @property
    def spacing(self) -> tuple[float, float]:
        """(dx, dy) pixel spacing, mm."""
        return self.grid.spacing

    @property
    def origin(self) -> tuple[float, float]:
        """(x, y) of pixel [0, 0]'s centre, mm, forward-model imaging-plane coordinates."""
        return self.grid.origin

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.shape

    def pixel_points(self) -> np.ndarray:
        """Pixel centres, (n_axial * n_lateral, 2) [x, y] mm, C order."""
        return self.grid.points()

    def _frame(self, k) -> int:
        if isinstance(k, bool) or int(k) != k or not 0 <= int(k) < self.n_frames:
            raise ValueError(f"frame index k must be an integer in [0, {self.n_frames}), got {k!r}")
        return int(k)

    def _interp(self, table: np.ndarray, points) -> np.ndarray:
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must be (n, 2) [x, y] mm, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points must be finite")
        fx, fy = self.field_x, self.field_y
        lo = np.array([fx[0], fy[0]]) - _TOL_OUTSIDE_MM
        hi = np.array([fx[-1], fy[-1]]) + _TOL_OUTSIDE_MM
        bad = np.any((p < lo) | (p > hi), axis=1)
        if np.any(bad):
            raise ValueError(f"{int(bad.sum())} points lie outside the stored true-field box x in "
                             f"[{fx[0]:g}, {fx[-1]:g}], y in [{fy[0]:g}, {fy[-1]:g}] mm (first: {p[bad][0]})")
        ci = (p[:, 0] - fx[0]) / (fx[1] - fx[0])
        cj = (p[:, 1] - fy[0]) / (fy[1] - fy[0])
        coords = np.vstack([ci, cj])
        return np.column_stack([scipy.ndimage.map_coordinates(table[..., c], coords, order=1, mode="nearest")
                                for c in range(table.shape[-1])])

    def true_displacement(self, k: int, points) -> np.ndarray:
        """True displacement frame 0 -> frame ``k`` at frame-0 ``points`` (n, 2) [x, y] mm -> (n, 2) [ux, uy] mm.

        Registration convention: ``frames[0](x) ~ frames[k](x + u(x))`` (up to speckle decorrelation and noise).
        Points may lie up to 0.5 mm outside the stored box (imaged area + 1 mm; clamped); further -> ValueError.
        """
        return self.scales[self._frame(k)] * self._interp(self.unit_displacement, points)

    def true_strain(self, k: int, points) -> np.ndarray:
        """True small strain frame 0 -> frame ``k`` at frame-0 ``points`` -> (n, 3) [exx, eyy, exy],
        ``exy = (dux/dy + duy/dx) / 2``."""
        return self.scales[self._frame(k)] * self._interp(self.unit_strain, points)

    def mean_axial_strain(self) -> np.ndarray:
        """Mean true ``exx`` over the imaged area (pixel centres) of every frame, (n_frames,) (negative =
        compression), measured from :meth:`true_strain`."""
        pts = self.pixel_points()
        return np.array([float(np.mean(self.true_strain(k, pts)[:, 0])) for k in range(self.n_frames)])

    def save(self, path) -> Path:
        """Write one self-describing ``.npz`` (frames, true-field tables, mask, JSON ``meta`` with every parameter
        and the seed).  Written to a temporary name and renamed, so a reader never sees a partial file."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = dict(self.params, format="femreg-rf-sequence", format_version=FORMAT_VERSION,
                    grid=self.grid.to_dict())
        # uncompressed: RF speckle hardly compresses and reading stays fast
        atomic_savez(path, writer=lambda tmp: np.savez(
            tmp, frames=self.frames, scales=self.scales, field_x=self.field_x, field_y=self.field_y,
            unit_displacement=self.unit_displacement, unit_strain=self.unit_strain,
            inclusion_mask=self.inclusion_mask, meta=np.array(json.dumps(meta, sort_keys=True))))
        self.path = path
        return path


def load_sequence(path) -> Sequence:
    """Read a file written by :meth:`Sequence.save`; :class:`femreg.errors.FileFormatError` if it is not one."""
    from femreg.errors import FileFormatError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no sequence file {str(path)!r}")
    keys = ("frames", "scales", "field_x", "field_y", "unit_displacement", "unit_strain", "inclusion_mask", "meta")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise FileFormatError(f"{path}: not an RF sequence file (missing {', '.join(missing)})")
            data = {k: z[k] for k in keys}
        meta = json.loads(str(data.pop("meta")))
    except FileFormatError:
        raise
    except Exception as exc:  # zip/npy/json corruption
        raise FileFormatError(f"{path}: unreadable RF sequence file ({type(exc).__name__}: {exc})") from None
    if meta.get("format") != "femreg-rf-sequence":
        raise FileFormatError(f"{path}: not an RF sequence file (format {meta.get('format')!r})")
    grid = ImagingGrid(**meta.pop("grid"))
    frames = data["frames"]
    if frames.ndim != 3 or frames.shape[1:] != grid.shape or len(data["scales"]) != frames.shape[0]:
        raise FileFormatError(f"{path}: frames {frames.shape} do not match the grid {grid.shape}")
    meta.pop("format", None)
    meta.pop("format_version", None)
    return Sequence(frames=frames, grid=grid, scales=data["scales"], field_x=data["field_x"],
                    field_y=data["field_y"], unit_displacement=data["unit_displacement"],
                    unit_strain=data["unit_strain"], inclusion_mask=data["inclusion_mask"].astype(bool),
                    params=meta, path=path)


def schedule_figures(seq: Sequence) -> dict:
    """The compression schedule measured from the true strain: mean ``-exx`` over the imaged area.

    Returns a dict of percentages: ``cumulative`` (per frame, from frame 1 = index 0), ``total`` (frame 1 ->
    last), ``mean_step``, ``max_step`` (frame to frame), ``frames_1_3``, ``frames_1_7``, ``frames_1_10`` (where the
    sequence has those frames).
    """
    cum = -100.0 * seq.mean_axial_strain()
    cum = cum - cum[0]
    steps = np.diff(cum)
    out = {"cumulative": [round(float(c), 6) for c in cum], "total": float(cum[-1])}
    if len(steps):
        out.update(mean_step=float(steps.mean()), max_step=float(steps.max()), min_step=float(steps.min()))
    for a, b in ((1, 3), (1, 7), (1, 10)):
        if b <= len(cum):
            out[f"frames_{a}_{b}"] = float(cum[b - 1] - cum[a - 1])
    return out


def _field_grid(grid: ImagingGrid, spacing_mm: float, pad_mm: float = 1.0):
    x0, x1, y0, y1 = grid.extent()
    top = max(0.0, x0 - pad_mm) if grid.x0 >= 0 else x0 - pad_mm  # no tissue above the top face x = 0
    nx = int(math.ceil((x1 + pad_mm - top) / spacing_mm)) + 1
    ny = int(math.ceil((y1 - y0 + 2 * pad_mm) / spacing_mm)) + 1
    fx = top + spacing_mm * np.arange(nx)
    fy = 0.5 * (y0 + y1) + spacing_mm * (np.arange(ny) - (ny - 1) / 2)
    return fx, fy


def simulate_sequence(model: str = "3d", inclusion: str = "HI", n_frames: int = 20, seed: int = 0,
                      snr_db: float | None = 12.0, *, density_per_mm2: float = 30.0, spacing=None,
                      depth_mm: float = 72.0, width_mm: float = 44.0, psf: PSF | dict | None = None,
                      strain_schedule=None, field=None, fe_options: dict | None = None,
                      background_modulus: float = BACKGROUND_MODULUS, inclusion_depth_mm: float = 30.0,
                      inclusion_diameter_mm: float = 15.0, field_grid_spacing_mm: float = 0.1,
                      verbose: bool = False) -> Sequence:
    """Simulate an RF sequence of a forward model under the paper's compression schedule.

    Parameters
    ----------
    model : {"3d", "plane-strain", "plane-stress"}
        Forward model (issue 2).
    inclusion : {"HI", "mHI", "HOM", "SI"}
        Inclusion modulus 40 / 20 / 10 / 5 MPa (background ``background_modulus``, 10 MPa).
    n_frames : int
        Number of frames (paper: 20).  Frame 0 is undeformed.
    seed : int
        Seed of everything random (scatterers, amplitudes, noise; ``numpy.random.SeedSequence(seed)``).
    snr_db : float or None
        ``10 log10(P_s / sigma_n^2)``, ``P_s`` the mean square of noise-free frame 0 over the frame; the same noise
        level ``sigma_n`` (fresh noise) in every frame.  ``None``: no noise.  Paper: 12 dB.
    density_per_mm2 : float
        Scatterer density (paper: 30 per mm^2).
    spacing : (dx, dy) or None
        Pixel spacing, mm; default ``(c / (2 * 40 MHz), 0.3)`` = (0.01925, 0.3).
    depth_mm, width_mm : float
        Imaged area: ``depth_mm`` from the top face down, ``width_mm`` centred laterally (paper: 72 x 44 mm).
    psf : PSF or dict, optional
        Point spread function (default: the paper's, see :class:`forward.ultrasound.PSF`).
    strain_schedule : (n_frames,) array, optional
        Cumulative mean axial compressive strain (fraction) of each frame, starting at 0; default
        :func:`paper_schedule`.
    field : object, optional
        Any object with ``displacement(points)`` and ``strain(points)`` at unit (1 mm) compression, replacing the
        FE solve (e.g. :class:`AnalyticField`); recorded as ``field_source="custom"``.
    fe_options : dict, optional
        Extra keyword arguments of ``forward.solve_elasticity`` (mesh size, ...); part of the cache key.
    background_modulus, inclusion_depth_mm, inclusion_diameter_mm : float
        Forward-model parameters (MPa, mm); the inclusion disk also sets the doubled-amplitude region and the mask.
    field_grid_spacing_mm : float
        Spacing of the stored true-field grid (module docstring).

    Returns
    -------
    Sequence
    """
    t_start = time.perf_counter()
    _check_model(model)
    _check_inclusion(inclusion)
    n_frames = _check_n_frames(n_frames)
    if isinstance(seed, bool) or int(seed) != seed or int(seed) < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    if snr_db is not None:
        try:
            snr_ok = math.isfinite(float(snr_db))
        except (TypeError, ValueError):
            snr_ok = False
        if not snr_ok:
            raise ValueError(f"snr_db must be a finite number of dB (or None for no noise), got {snr_db!r}")
        snr_db = float(snr_db)
    try:
        density_ok = math.isfinite(float(density_per_mm2)) and float(density_per_mm2) > 0
    except (TypeError, ValueError):
        density_ok = False
    if not density_ok:
        raise ValueError(f"density_per_mm2 must be a positive finite number of scatterers per mm^2, got "
                         f"{density_per_mm2!r}")
    psf = PSF(**psf) if isinstance(psf, dict) else (PSF() if psf is None else psf)
    grid = ImagingGrid.centred(depth_mm=depth_mm, width_mm=width_mm, spacing=spacing,
                               speed_of_sound_mm_per_s=psf.speed_of_sound_mm_per_s)
    gs = float(field_grid_spacing_mm)
    if not math.isfinite(gs) or gs <= 0:
        raise ValueError(f"field_grid_spacing_mm must be positive, got {field_grid_spacing_mm!r}")
    for name, v in (("background_modulus", background_modulus), ("inclusion_depth_mm", inclusion_depth_mm),
                    ("inclusion_diameter_mm", inclusion_diameter_mm)):
        if not math.isfinite(float(v)) or float(v) <= 0:
            raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    if strain_schedule is None:
        schedule = paper_schedule(n_frames)
    else:
        schedule = np.asarray(strain_schedule, dtype=float)
        if schedule.shape != (n_frames,) or not np.all(np.isfinite(schedule)) or schedule[0] != 0:
            raise ValueError(f"strain_schedule must be {n_frames} finite cumulative strains starting at 0, got "
                             f"shape {schedule.shape}")
    fe_options = dict(fe_options or {})
    inclusion_modulus = INCLUSIONS[inclusion]
    inc_center = (float(inclusion_depth_mm), 0.0)
    inc_radius = float(inclusion_diameter_mm) / 2.0
    log = print if verbose else (lambda *a, **k: None)

    # 1. The forward field at unit compression (one solve per model).
    t0 = time.perf_counter()
    if field is None:
        field, source = _fe_field(model, inclusion_modulus, float(background_modulus), inc_center[0],
                                  float(inclusion_diameter_mm), fe_options)
    else:
        if not (callable(getattr(field, "displacement", None)) and callable(getattr(field, "strain", None))):
            raise ValueError("field must have displacement(points) and strain(points) methods")
        source = "custom" if not isinstance(field, AnalyticField) else "analytic"
    t_solve = time.perf_counter() - t0

    # 2. True fields on the stored grid; scale factors from the mean axial strain over the imaged area.
    t0 = time.perf_counter()
    fx, fy = _field_grid(grid, gs)
    FX, FY = np.meshgrid(fx, fy, indexing="ij")
    u_tab, e_tab = _eval_field(field, np.column_stack([FX.ravel(), FY.ravel()]))
    seq = Sequence(frames=np.zeros((0,) + grid.shape, np.float32), grid=grid, scales=np.ones(1), field_x=fx,
                   field_y=fy, unit_displacement=u_tab.reshape(len(fx), len(fy), 2),
                   unit_strain=e_tab.reshape(len(fx), len(fy), 3), inclusion_mask=np.zeros(grid.shape, bool))
    mean_exx_unit = float(np.mean(seq._interp(seq.unit_strain, grid.points())[:, 0]))
    if not mean_exx_unit < 0:
        raise ValueError(f"the forward field does not compress the imaged area (mean exx = {mean_exx_unit:g} "
                         "at unit compression)")
    scales = schedule / -mean_exx_unit
    t_tables = time.perf_counter() - t0

    # 3. Scatterers over the imaged area plus the margin they can move across; displacement at their positions.
    t0 = time.perf_counter()
    ss_scat, ss_noise = np.random.SeedSequence(seed).spawn(2)
    s_max = float(np.max(np.abs(scales)))
    hx, hy = psf.half_support_mm()
    mx = s_max * float(np.max(np.abs(u_tab[:, 0]))) + hx + 0.5
    my = s_max * float(np.max(np.abs(u_tab[:, 1]))) + hy + 0.5
    x0, x1, y0, y1 = grid.extent()
    box = (max(0.0, x0 - mx), x1 + mx, y0 - my, y1 + my)  # tissue starts at the top face x = 0
    scat = make_scatterers(np.random.default_rng(ss_scat), box, density_per_mm2=density_per_mm2,
                           inclusion_center=inc_center, inclusion_radius_mm=inc_radius,
                           cell_aspect=psf.sigma_axial_mm / psf.sigma_lateral_mm)
    u_scat = _eval_displacement(field, scat.positions)
    t_scat = time.perf_counter() - t0

    # 4. Frames: the same scatterers moved by s_k U(X); noise at a fixed level set by frame 0.
    t0 = time.perf_counter()
    frames = np.empty((n_frames,) + grid.shape, np.float32)
    noise_rngs = [np.random.default_rng(s) for s in ss_noise.spawn(n_frames)]
    sigma_n = None
    signal_power = None
    for k in range(n_frames):
        clean = render_rf(scat.positions + scales[k] * u_scat, scat.amplitudes, grid, psf)
        if k == 0:
            signal_power = float(np.mean(clean**2))
            sigma_n = 0.0 if snr_db is None else noise_sigma(signal_power, snr_db)
        frames[k] = clean if snr_db is None else add_noise(clean, snr_db, noise_rngs[k], signal_power=signal_power)
        log(f"  frame {k + 1}/{n_frames} rendered")
    t_render = time.perf_counter() - t0

    X, Y = np.meshgrid(grid.x, grid.y, indexing="ij")
    seq.inclusion_mask = (X - inc_center[0]) ** 2 + (Y - inc_center[1]) ** 2 < inc_radius**2
    seq.frames = frames
    seq.scales = scales
    seq.params = dict(
        model=model, inclusion=inclusion, inclusion_modulus=inclusion_modulus,
        background_modulus=float(background_modulus), inclusion_depth_mm=inc_center[0],
        inclusion_diameter_mm=float(inclusion_diameter_mm), n_frames=n_frames, seed=seed, snr_db=snr_db,
        density_per_mm2=float(density_per_mm2), spacing=list(grid.spacing), depth_mm=float(depth_mm),
        width_mm=float(width_mm), psf=psf.to_dict(), strain_schedule=[float(s) for s in schedule],
        compression_mm=[float(s) for s in scales], mean_exx_unit=mean_exx_unit, field_source=source,
        fe_options=fe_options, field_grid_spacing_mm=gs, scatterer_box_mm=list(box), n_scatterers=len(scat),
        amplitude_distribution="standard normal, x2 inside the inclusion", signal_power=signal_power,
        noise_sigma=sigma_n, snr_definition="10 log10(mean(clean frame 0 ^2) / sigma_n^2), same sigma_n all frames",
        timings_s=dict(solve=t_solve, field_tables=t_tables, scatterers=t_scat, render=t_render,
                       total=time.perf_counter() - t_start),
    )
    log(f"  {model}/{inclusion}: {len(scat)} scatterers, render {t_render:.1f} s, total "
        f"{time.perf_counter() - t_start:.1f} s")
    return seq


# --------------------------------------------------------------------------------------------------------------
# Cache and the paper's data sets
# --------------------------------------------------------------------------------------------------------------

def sequence_cache_dir(cache_dir=None) -> Path:
    """Directory of cached sequences: ``cache_dir`` if given, else :func:`forward.elasticity.cache_dir`
    ``/sequences``."""
    if cache_dir is not None:
        return Path(cache_dir)
    from .elasticity import cache_dir as _cache_root

    return _cache_root() / "sequences"


def _cache_key(model, inclusion, kwargs: dict) -> str:
    def norm(v):
        if isinstance(v, PSF):
            return v.to_dict()
        if isinstance(v, np.ndarray):
            return v.tolist()
        return v

    blob = json.dumps({"model": model, "inclusion": inclusion, "version": FORMAT_VERSION,
                       **{k: norm(v) for k, v in sorted(kwargs.items())}}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def get_sequence(model: str = "3d", inclusion: str = "HI", *, seed: int = 0, snr_db: float | None = 12.0,
                 n_frames: int = 20, cache_dir=None, refresh: bool = False, verbose: bool = False,
                 **kwargs) -> Sequence:
    """:func:`simulate_sequence` with a disk cache: the same arguments return the file written the first time.

    The file is ``<cache>/<model>-<inclusion>_seed<seed>_<hash>.npz``, the hash over every argument and
    :data:`FORMAT_VERSION`.  ``refresh=True`` re-simulates.  ``field=`` (a custom field) is not cacheable.
    """
    if "field" in kwargs:
        raise ValueError("get_sequence caches FE-based sequences only; call simulate_sequence(field=...) instead")
    name = dataset_name(model, inclusion)
    args = dict(seed=seed, snr_db=snr_db, n_frames=n_frames, **kwargs)
    # Key over the full argument set with defaults filled in, so equivalent calls share one file.
    bound = inspect.signature(simulate_sequence).bind(model, inclusion, **args)
    bound.apply_defaults()
    key_args = {k: v for k, v in bound.arguments.items() if k not in ("model", "inclusion", "verbose")}
    key_args["psf"] = (PSF(**key_args["psf"]) if isinstance(key_args["psf"], dict)
                       else key_args["psf"] or PSF()).to_dict()
    key_args["fe_options"] = dict(key_args["fe_options"] or {})
    if key_args["snr_db"] is not None:
        key_args["snr_db"] = float(key_args["snr_db"])
    key_args["fe_cache_key"] = _fe_cache_key(
        model, inclusion_modulus=INCLUSIONS[_check_inclusion(inclusion)],
        background_modulus=key_args["background_modulus"], inclusion_depth_mm=key_args["inclusion_depth_mm"],
        inclusion_diameter_mm=key_args["inclusion_diameter_mm"], fe_options=key_args["fe_options"])
    path = sequence_cache_dir(cache_dir) / f"{name}_seed{seed}_{_cache_key(model, inclusion, key_args)}.npz"
    if path.is_file() and not refresh:
        try:
            return load_sequence(path)
        except ValueError:
            pass  # corrupt cache entry: regenerate
    seq = simulate_sequence(model, inclusion, verbose=verbose, **args)
    seq.save(path)
    return seq


def paper_datasets(names=None, *, seed: int = 0, snr_db: float | None = 12.0, cache_dir=None,
                   refresh: bool = False, verbose: bool = False, **kwargs) -> dict:
    """The paper's six sequences (cached): ``{"3d-HI": Sequence, "3d-mHI": ..., "3d-HOM", "3d-SI",
    "plane-strain-HI", "plane-stress-HI"}``; ``names`` selects a subset (ValueError naming an unknown one)."""
    if names is None:
        pairs = list(PAPER_DATASETS)
    else:
        pairs = [parse_dataset_name(n) for n in ([names] if isinstance(names, str) else names)]
    return {dataset_name(m, i): get_sequence(m, i, seed=seed, snr_db=snr_db, cache_dir=cache_dir,
                                             refresh=refresh, verbose=verbose, **kwargs) for m, i in pairs}
