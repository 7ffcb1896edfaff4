"""Probe geometries: the mappings between sample indices and physical Cartesian coordinates (x depth, y lateral,
z elevational, mm) of convex and phased (sector) arrays (2D frames, :class:`Convex`, :class:`Sector`) and of
mechanically swept 3D probes (volumes, :class:`Swept`).  Pure mappings: the registrations that use them are
:mod:`femreg.geometry` (frames) and :mod:`femreg.swept` (volumes).

A swept probe is a linear or curved array rocked in elevation by a motor: each frame ``k`` lies in a plane
tilted by ``phi_k = (k - (n_frames - 1) / 2) dphi`` about an axis parallel to y at ``sweep_radius_mm`` behind the
face (``(x, z) = (-R_s, 0)``).  In its plane the frame is the array's 2D frame (:class:`Convex` conventions, or a
linear array: lines ``y_j = y_0 + j dy`` straight down), at in-plane depth ``a`` and lateral position ``y``; the
tilt maps ``(a, phi)`` to ``(x, z)`` exactly as a convex array maps (range, angle) to (x, y), with the sweep
radius as the apex distance: ``x = (R_s + a) cos(phi) - R_s``, ``z = (R_s + a) sin(phi)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, pass_as

__all__ = ["Convex", "Sector", "Swept", "as_geometry"]


@dataclass(frozen=True)
class Convex:
    """A convex (curvilinear) array: rays from an apex ``radius_mm`` behind the face, ``angle_pitch_deg`` apart.

    See the module docstring for the conventions (range from the face along the ray, angle 0 along x, positive
    towards +y, rays centred on 0).  ``radius_mm`` > 0 mm (40-60 mm abdominal probes); ``angle_pitch_deg`` > 0."""

    radius_mm: float = 50.0
    angle_pitch_deg: float = 0.5

    def __post_init__(self):
        r, a = self.radius_mm, self.angle_pitch_deg
        ok_r = isinstance(r, (int, float)) and np.isfinite(r) and r >= (0 if self.kind == "sector" else 1e-9)
        if not ok_r:
            raise InputError(pass_as(f"{self.kind} radius_mm must be a finite number > 0 mm, got {r!r}",
                                     f"--geometry {self.kind} needs --radius > 0 mm, got {r!r}"))
        if not (isinstance(a, (int, float)) and np.isfinite(a) and 0 < a < 10):
            raise InputError(pass_as(f"{self.kind} angle_pitch_deg must be a number in (0, 10) degrees, got {a!r}",
                                     f"--geometry {self.kind} needs --angle-pitch above 0 and below 10 degrees, "
                                     f"got {a!r}"))

    kind = "convex"

    @property
    def pitch_rad(self) -> float:
        return float(np.deg2rad(self.angle_pitch_deg))

    # -- the mapping ---------------------------------------------------------------------------------------
    def angles(self, n_rays: int) -> np.ndarray:
        """Ray angles (n_rays,) rad, centred on 0."""
        return (np.arange(int(n_rays)) - 0.5 * (int(n_rays) - 1)) * self.pitch_rad

    def to_physical(self, r, theta):
        """(range mm from the face, angle rad) -> (x, y) mm; any broadcastable shapes."""
        rho = self.radius_mm + np.asarray(r, float)
        theta = np.asarray(theta, float)
        return rho * np.cos(theta) - self.radius_mm, rho * np.sin(theta)

    def to_beam(self, x, y):
        """(x, y) mm -> (range mm from the face, angle rad); the inverse of :meth:`to_physical`."""
        xa = np.asarray(x, float) + self.radius_mm
        y = np.asarray(y, float)
        return np.hypot(xa, y) - self.radius_mm, np.arctan2(y, xa)

    def jacobian(self, r, theta) -> np.ndarray:
        """d(x, y)/d(r, theta) at (r, theta), (..., 2, 2): [[cos, -rho sin], [sin, rho cos]]."""
        rho = self.radius_mm + np.asarray(r, float)
        c, s = np.cos(theta), np.sin(theta)
        return np.stack([np.stack([c, -rho * s], -1), np.stack([s, rho * c], -1)], -2)

    def index_to_physical(self, idx, shape, spacing, origin) -> np.ndarray:
        """Fractional sample indices ``idx`` (2, n) -> physical points (n, 2) mm (``spacing[0]`` = dr,
        ``origin[0]`` = r_0; the lateral entries are not used: the angles come from the pitch)."""
        idx = np.asarray(idx, float)
        r = origin[0] + idx[0] * spacing[0]
        th = (idx[1] - 0.5 * (shape[1] - 1)) * self.pitch_rad
        x, y = self.to_physical(r, th)
        return np.column_stack([x, y])

    def physical_to_index(self, points, shape, spacing, origin) -> np.ndarray:
        """Physical points (n, 2) mm -> fractional sample indices (2, n) (the inverse of
        :meth:`index_to_physical`)."""
        p = np.asarray(points, float).reshape(-1, 2)
        r, th = self.to_beam(p[:, 0], p[:, 1])
        return np.stack([(r - origin[0]) / spacing[0], th / self.pitch_rad + 0.5 * (shape[1] - 1)])

    def sample_positions(self, shape, spacing, origin) -> tuple:
        """Physical positions of every sample: ``(X, Y)``, each ``shape`` (n_samples, n_rays), mm."""
        i, j = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
        p = self.index_to_physical(np.stack([i.ravel(), j.ravel()]), shape, spacing, origin)
        return p[:, 0].reshape(shape), p[:, 1].reshape(shape)

    def ray_angle(self, points) -> np.ndarray:
        """Angle (n,) rad of the ray through each physical point (n, 2) mm."""
        p = np.asarray(points, float).reshape(-1, 2)
        return np.arctan2(p[:, 1], p[:, 0] + self.radius_mm)

    def to_dict(self) -> dict:
        return dict(kind=self.kind, radius_mm=float(self.radius_mm), angle_pitch_deg=float(self.angle_pitch_deg))


@dataclass(frozen=True)
class Sector(Convex):
    """A phased array (sector scan): the apex lies on the face (``radius_mm`` = 0), rays ``angle_pitch_deg``
    apart.  Conventions as :class:`Convex` (range from the apex = the face)."""

    radius_mm: float = 0.0
    angle_pitch_deg: float = 0.5
    kind = "sector"



@dataclass(frozen=True)
class Swept:
    """A mechanically swept 3D probe: ``array`` (None or "linear": a linear array; :class:`Convex` /
    :class:`Sector` or its dict: a curved one) rocked in elevation about an axis parallel to y, ``sweep_radius_mm``
    (>= 0; 0: the axis on the face) behind the face, frames ``angle_step_deg`` apart and centred on 0 (module
    docstring).  A volume is ``(n_samples, n_lines, n_frames)``: sample ``[i, j, k]`` is at range
    ``r_0 + i dr`` along line ``j`` of frame ``k``.  A line coordinate ``l`` is mm (linear array: ``y``) or rad
    (curved array: the ray angle)."""

    sweep_radius_mm: float = 0.0
    angle_step_deg: float = 1.0
    array: object = None

    kind = "swept"

    def __post_init__(self):
        r, a = self.sweep_radius_mm, self.angle_step_deg
        if not (isinstance(r, (int, float)) and np.isfinite(r) and r >= 0):
            raise InputError(f"swept sweep_radius_mm must be a finite number >= 0 mm, got {r!r}")
        if not (isinstance(a, (int, float)) and np.isfinite(a) and 0 < a < 10):
            raise InputError(f"swept angle_step_deg must be a number in (0, 10) degrees, got {a!r}")
        if isinstance(self.array, Swept) or (isinstance(self.array, dict) and self.array.get("kind") == "swept"):
            raise InputError("the array of a swept probe is linear, convex or sector, not swept")
        object.__setattr__(self, "array", as_geometry(self.array))

    @property
    def step_rad(self) -> float:
        return float(np.deg2rad(self.angle_step_deg))

    @property
    def sweep(self) -> Convex:
        """The tilt as a 2D mapping (in-plane depth a, phi) -> (x, z): a :class:`Convex` with the sweep radius
        as its apex distance (:class:`Sector` for 0)."""
        if self.sweep_radius_mm == 0:
            return Sector(angle_pitch_deg=self.angle_step_deg)
        return Convex(radius_mm=self.sweep_radius_mm, angle_pitch_deg=self.angle_step_deg)

    def frame_angles(self, n_frames: int) -> np.ndarray:
        """Frame tilts (n_frames,) rad, centred on 0."""
        return self.sweep.angles(n_frames)

    # -- the mapping -----------------------------------------------------------------------------------------
    def to_physical(self, r, line, phi):
        """(range mm from the face, line coordinate (mm or rad), tilt rad) -> (x, y, z) mm; broadcastable."""
        r, line = np.asarray(r, float), np.asarray(line, float)
        a, y = (r, line) if self.array is None else self.array.to_physical(r, line)
        x, z = self.sweep.to_physical(a, phi)
        return x, np.broadcast_to(y, np.broadcast(x, y).shape), z

    def to_beam(self, x, y, z):
        """(x, y, z) mm -> (range mm, line coordinate, tilt rad); the inverse of :meth:`to_physical`."""
        a, phi = self.sweep.to_beam(x, z)
        y = np.asarray(y, float)
        r, line = (a, y) if self.array is None else self.array.to_beam(a, y)
        return r, np.broadcast_to(line, np.broadcast(r, line).shape), phi

    def jacobian(self, r, line, phi) -> np.ndarray:
        """d(x, y, z)/d(r, line, phi) at the given beam coordinates, (..., 3, 3): the array's in-plane Jacobian
        d(a, y)/d(r, line) followed by the tilt's d(x, z)/d(a, phi)."""
        r, line, phi = np.broadcast_arrays(np.asarray(r, float), np.asarray(line, float), np.asarray(phi, float))
        if self.array is None:
            a = r
            Ja = np.broadcast_to(np.eye(2), r.shape + (2, 2))
        else:
            a = self.array.to_physical(r, line)[0]
            Ja = self.array.jacobian(r, line)
        Js = self.sweep.jacobian(a, phi)
        J = np.zeros(r.shape + (3, 3))
        J[..., 0, :2] = Js[..., 0, 0, None] * Ja[..., 0, :]
        J[..., 0, 2] = Js[..., 0, 1]
        J[..., 1, :2] = Ja[..., 1, :]
        J[..., 2, :2] = Js[..., 1, 0, None] * Ja[..., 0, :]
        J[..., 2, 2] = Js[..., 1, 1]
        return J

    def beam_axes(self, points) -> np.ndarray:
        """Unit vectors along the ray, across the lines and across the frames at physical ``points`` (n, 3) mm:
        (n, 3, 3), the columns of the normalised Jacobian (orthogonal for these mappings)."""
        p = np.asarray(points, float).reshape(-1, 3)
        J = self.jacobian(*self.to_beam(p[:, 0], p[:, 1], p[:, 2]))
        return J / np.linalg.norm(J, axis=-2, keepdims=True)

    def _line(self, j, shape, spacing, origin):
        if self.array is None:
            return origin[1] + np.asarray(j, float) * spacing[1]
        return (np.asarray(j, float) - 0.5 * (shape[1] - 1)) * self.array.pitch_rad

    def index_to_physical(self, idx, shape, spacing, origin) -> np.ndarray:
        """Fractional sample indices ``idx`` (3, n) -> physical points (n, 3) mm (``spacing[0]`` = dr,
        ``origin[0]`` = r_0; a linear array's ``spacing[1]`` / ``origin[1]`` = line pitch / first line mm; the
        angles come from the pitches)."""
        idx = np.asarray(idx, float)
        r = origin[0] + idx[0] * spacing[0]
        phi = (idx[2] - 0.5 * (shape[2] - 1)) * self.step_rad
        return np.column_stack(self.to_physical(r, self._line(idx[1], shape, spacing, origin), phi))

    def physical_to_index(self, points, shape, spacing, origin) -> np.ndarray:
        """Physical points (n, 3) mm -> fractional sample indices (3, n) (the inverse of
        :meth:`index_to_physical`)."""
        p = np.asarray(points, float).reshape(-1, 3)
        r, line, phi = self.to_beam(p[:, 0], p[:, 1], p[:, 2])
        j = (line - origin[1]) / spacing[1] if self.array is None else \
            line / self.array.pitch_rad + 0.5 * (shape[1] - 1)
        return np.stack([(r - origin[0]) / spacing[0], j, phi / self.step_rad + 0.5 * (shape[2] - 1)])

    def sample_positions(self, shape, spacing, origin) -> tuple:
        """Physical positions of every sample: ``(X, Y, Z)``, each ``shape`` (n_samples, n_lines, n_frames)."""
        i, j, k = (np.arange(n, dtype=float) for n in shape)
        r = (origin[0] + i * spacing[0])[:, None, None]
        line = self._line(j, shape, spacing, origin)[None, :, None]
        phi = self.frame_angles(shape[2])[None, None, :]
        return tuple(np.ascontiguousarray(np.broadcast_to(c, tuple(shape)))
                     for c in self.to_physical(r, line, phi))

    def to_dict(self) -> dict:
        return dict(kind=self.kind, sweep_radius_mm=float(self.sweep_radius_mm),
                    angle_step_deg=float(self.angle_step_deg),
                    array="linear" if self.array is None else self.array.to_dict())


def as_geometry(spec):
    """A :class:`Convex` / :class:`Sector` / :class:`Swept` from itself, or from a dict ``{"kind":
    "convex"|"sector"|"swept", ...}`` (:meth:`to_dict`); None (and "linear") for a linear array."""
    if spec is None or (isinstance(spec, str) and spec == "linear"):
        return None
    if isinstance(spec, (Convex, Swept)):
        return spec
    if isinstance(spec, dict):
        d = dict(spec)
        kind = d.pop("kind", "convex")
        if kind == "linear":
            return None
        cls = {"convex": Convex, "sector": Sector, "swept": Swept}.get(kind)
        if cls is None:
            raise InputError(f"geometry kind must be 'linear', 'convex', 'sector' or 'swept', got {kind!r}")
        try:
            return cls(**d)
        except TypeError as exc:
            raise InputError(f"bad {kind} geometry: {exc}") from None
    raise InputError(f"geometry must be femreg.Convex(...), femreg.Sector(...), femreg.Swept(...) or None, got "
                     f"{spec!r}")
