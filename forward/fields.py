"""Displacement fields with exact truth for simulated RF pairs: affine (compression, shear, rotation), bending,
layers sliding across a shear band, bonded layers, columns sliding along vertical interfaces, and FE inclusions
(plane strain / plane stress).

Every field is an object with

* ``displacement(points)``: (n, 2) [x, y] mm -> (n, 2) [u_x, u_y] mm, the motion of the tissue point at ``points``
  in the reference frame (registration convention ``reference(x) ~ moving(x + u(x))``);
* ``strain(points)``: (n, 3) [e_xx, e_yy, e_xy] with ``e = (grad u + grad u^T) / 2`` of that same ``u`` (small
  strain, ``e_xy = (du_x/dy + du_y/dx) / 2``), exact: closed form for the analytic fields, the FE solution's own
  gradient for the inclusions;
* ``level``: the nominal mean axial compressive strain (fraction, >= 0) and ``at(level)``, the same kind of field at
  another level (sequences, :func:`forward.pairs.make_sequence`);
* ``name``: short label.

Coordinates: ``x`` depth below the probe face (axial), ``y`` lateral from the centre line (mm).  The probe face is the
reference of the motion: tissue touching the probe (``x = 0``) does not move axially and deeper tissue moves
towards the probe (``u_x = -s x`` for uniform compression ``s``), which is what a hand-held probe records.  So the
largest axial motion grows with depth: ``s`` times the deepest imaged point.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["Affine", "translation", "compression", "shear_rotation", "compression_rotation", "Bending", "ShearBand",
           "Layers", "SlidingColumns", "Inclusion", "as_points", "imaged_points", "LoopTruth"]


def as_points(points) -> np.ndarray:
    """``points`` as a float (n, 2) array; ValueError naming the shape otherwise."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points must be an (n, 2) array of [x, y] mm, got shape {p.shape}")
    return p


def imaged_points(motion, x, tol: float = 1e-12, maxiter: int = 60) -> np.ndarray:
    """The tissue points X a frame images at ``x`` (n, 2) mm: the fixed point of ``motion(X) = x`` by the iteration
    X <- X - (motion(X) - x), from X = x (``motion``: tissue point -> where the frame images it, a small
    deformation of the identity); stops when no point moves by more than ``tol`` mm."""
    x = np.asarray(x, float)
    X = np.array(x, float)
    for _ in range(int(maxiter)):
        Xn = X - (motion(X) - x)
        if np.max(np.abs(Xn - X)) < tol:
            return Xn
        X = Xn
    return X


class LoopTruth:
    """The exact truth of a loop given by ``motion(k, X)``: where frame k images the tissue point X (frame-0
    coordinates, (n, 2) mm).  ``displacement(i, j, x)``: frame i -> j at frame-i points x (n, 2) mm;
    ``strain(i, j, x, h)``: its small strain [e_xx, e_yy, e_xy] by central differences of step h mm."""

    def __init__(self, motion):
        self.motion = motion

    def displacement(self, i, j, x) -> np.ndarray:
        X = imaged_points(lambda P: self.motion(i, P), x)
        return self.motion(j, X) - self.motion(i, X)

    def strain(self, i, j, x, h: float = 1e-4) -> np.ndarray:
        x = np.asarray(x, float)
        gx = (self.displacement(i, j, x + [h, 0]) - self.displacement(i, j, x - [h, 0])) / (2 * h)
        gy = (self.displacement(i, j, x + [0, h]) - self.displacement(i, j, x - [0, h])) / (2 * h)
        return np.column_stack([gx[:, 0], gy[:, 1], 0.5 * (gy[:, 0] + gx[:, 1])])


def _level(level) -> float:
    try:
        v = float(level)
    except (TypeError, ValueError):
        raise ValueError(f"strain level must be a number (fraction, e.g. 0.01 for 1 %), got {level!r}") from None
    if not math.isfinite(v) or v < 0 or v >= 0.5:
        raise ValueError(f"strain level must be a fraction in [0, 0.5), got {level!r}")
    return v


class Affine:
    """``u(x) = t + G x`` (about the probe-face centre ``x = 0``): uniform strain ``sym G``, rotation ``skew G``
    and a rigid shift ``t``.

    Parameters
    ----------
    gradient : (2, 2) array
        Displacement gradient ``G[i, j] = du_i / dx_j`` ([x, y] order).
    shift : (2,) mm
        Rigid translation ``t`` = [t_x, t_y].
    level : float
        Nominal compressive axial strain (fraction) of this field, for ``at``.
    name : str
    builder : callable(level) -> Affine, optional
        How to make the same kind of field at another level (set by the factories below).
    """

    def __init__(self, gradient, *, shift=(0.0, 0.0), level: float = 0.0, name: str = "affine", builder=None):
        G = np.asarray(gradient, dtype=float)
        if G.shape != (2, 2) or not np.all(np.isfinite(G)):
            raise ValueError(f"gradient must be a finite (2, 2) array, got {G!r}")
        t = np.asarray(shift, dtype=float)
        if t.shape != (2,) or not np.all(np.isfinite(t)):
            raise ValueError(f"shift must be a finite (2,) [x, y] mm, got {shift!r}")
        self.G = G
        self.shift = t
        self.level = float(level)
        self.name = str(name)
        self._builder = builder

    def displacement(self, points) -> np.ndarray:
        return as_points(points) @ self.G.T + self.shift

    def strain(self, points) -> np.ndarray:
        p = as_points(points)
        G = self.G
        e = np.array([G[0, 0], G[1, 1], 0.5 * (G[0, 1] + G[1, 0])])
        return np.broadcast_to(e, (len(p), 3)).copy()

    def at(self, level) -> "Affine":
        if self._builder is None:
            s = _level(level) / self.level if self.level > 0 else 0.0
            return Affine(s * self.G, shift=s * self.shift, level=_level(level), name=self.name)
        return self._builder(_level(level))

    def __repr__(self) -> str:
        return f"Affine({self.name}, G={self.G.tolist()}, shift={self.shift.tolist()})"


def translation(tx_mm: float, ty_mm: float = 0.0) -> Affine:
    """Rigid shift ``u = (t_x, t_y)`` mm everywhere (zero strain)."""
    return Affine(np.zeros((2, 2)), shift=(tx_mm, ty_mm), name=f"shift ({tx_mm:g}, {ty_mm:g}) mm")


def compression(level: float) -> Affine:
    """Uniform axial compression ``s = level`` with the area-preserving (incompressible, plane strain) lateral
    expansion: ``u_x = -s x``, ``u_y = s / (1 - s) y`` (``(1 - s)(1 + s / (1 - s)) = 1``)."""
    s = _level(level)
    return Affine(np.diag([-s, s / (1.0 - s)]), level=s, name=f"compression {100 * s:g}%", builder=compression)


def shear_rotation(level: float = 0.01, *, shear: float | None = None, rotation_deg: float = 0.1) -> Affine:
    """Compression ``level`` (as :func:`compression`) plus simple shear ``u_x += shear * y`` (default
    ``0.6 * level``) and a rigid rotation by ``rotation_deg`` about the probe-face centre (exact rotation matrix,
    ``u = (R (I + G_0) - I) x``).  ``at`` scales the shear and the rotation with the level."""
    s = _level(level)
    g = 0.6 * s if shear is None else float(shear)
    th = math.radians(float(rotation_deg))
    F0 = np.array([[1.0 - s, g], [0.0, 1.0 / (1.0 - s)]])
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    ratio = g / s if s > 0 else 0.6
    rot_per_level = float(rotation_deg) / s if s > 0 else 0.0
    return Affine(R @ F0 - np.eye(2), level=s,
                  name=f"compression {100 * s:g}% + shear {100 * g:g}% + rotation {rotation_deg:g} deg",
                  builder=lambda lv: shear_rotation(lv, shear=ratio * lv, rotation_deg=rot_per_level * lv))


def compression_rotation(level: float = 0.01, rotation_deg: float = 2.0) -> Affine:
    """Compression ``level`` (lateral expansion ``level / 2``) plus an in-plane rotation by ``rotation_deg`` about
    the probe-face centre, added to it: ``u = (R - I) x + diag(-s, s / 2) x`` with the exact rotation matrix R.
    Unlike :func:`shear_rotation` (``R F_0 - I``: the rotation turns the compressed block) the strain is
    ``diag(cos - 1 - s, cos - 1 + s / 2)``, no shear.  The rotated pairs of ``benchmarks/rotation_sweep.py``."""
    s = _level(level)
    th = math.radians(float(rotation_deg))
    c, sn = math.cos(th), math.sin(th)
    return Affine(np.array([[c - 1.0 - s, -sn], [sn, c - 1.0 + 0.5 * s]]), level=s,
                  name=f"compression {100 * s:g}% + rotation {rotation_deg:g} deg")


class Bending:
    """Axial strain varying linearly across the image, as in a bent or obliquely pressed block.

    ``e_xx(y) = -(e_0 + g (y - y_c))`` with ``e_0 = (s_1 + s_2) / 2``, ``g = (s_2 - s_1) / W``, so the compression is
    ``s_1`` at ``y = y_c - W/2`` and ``s_2`` at ``y = y_c + W/2``; displacement

    ``u_x = -(e_0 + g (y - y_c)) x``,  ``u_y = e_0 (y - y_c) + g (y - y_c)^2 / 2``,

    divergence-free (``e_xx + e_yy = 0``), with shear strain ``e_xy = -g x / 2`` growing with depth.
    ``level`` = mean compression ``e_0``; ``at`` scales ``s_1`` and ``s_2`` together.
    """

    def __init__(self, s1: float = 0.002, s2: float = 0.02, width_mm: float = 40.0, y_centre_mm: float = 0.0):
        self.s1, self.s2 = float(s1), float(s2)
        self.W = float(width_mm)
        if not self.W > 0:
            raise ValueError(f"width_mm must be positive, got {width_mm!r}")
        self.yc = float(y_centre_mm)
        self.e0 = 0.5 * (self.s1 + self.s2)
        self.g = (self.s2 - self.s1) / self.W
        self.level = self.e0
        self.name = f"bending {100 * self.s1:g}-{100 * self.s2:g}%"

    def displacement(self, points) -> np.ndarray:
        p = as_points(points)
        y = p[:, 1] - self.yc
        return np.column_stack([-(self.e0 + self.g * y) * p[:, 0], self.e0 * y + 0.5 * self.g * y**2])

    def strain(self, points) -> np.ndarray:
        p = as_points(points)
        y = p[:, 1] - self.yc
        exx = -(self.e0 + self.g * y)
        return np.column_stack([exx, -exx, -0.5 * self.g * p[:, 0]])

    def at(self, level) -> "Bending":
        f = _level(level) / self.e0 if self.e0 > 0 else 0.0
        return Bending(f * self.s1, f * self.s2, self.W, self.yc)

    def __repr__(self) -> str:
        return f"Bending({self.name}, W={self.W:g} mm)"


class ShearBand:
    """Two layers sliding laterally past each other across a band parallel to the probe face, on top of uniform
    axial compression (:func:`compression`).

    Inside the band ``|x - d| < t / 2`` the tissue shears uniformly (a soft layer, e.g. fascia); above and below
    it moves rigidly with its layer, the deep layer ``slide`` mm further along ``+y`` than the shallow one:

    ``u_x = -s x``,  ``u_y = s / (1 - s) y + slide (r(x) - 1/2)``,  ``r = clip((x - d) / t + 1/2, 0, 1)``,

    so ``e_xx = -s``, ``e_yy = s / (1 - s)`` everywhere and ``e_xy = slide / (2 t)`` inside the band, 0 outside
    (the integral of ``2 e_xy`` across the band is ``slide``).  At the band's two faces the shear strain steps (the
    band is bonded to its layers: ``u`` is continuous, its gradient is not).

    Parameters
    ----------
    depth_mm : float
        Depth ``d`` of the band's centre below the probe face, mm.
    thickness_mm : float
        Band thickness ``t``, mm (> 0).
    slide_mm : float
        Lateral slide of the deep layer relative to the shallow one, mm.
    level : float
        Axial compression (fraction); ``at(level)`` scales the slide with it (the slide per unit compression).
    """

    def __init__(self, depth_mm: float = 15.0, thickness_mm: float = 1.0, slide_mm: float = 0.15,
                 level: float = 0.01):
        self.depth_mm, self.thickness_mm, self.slide_mm = float(depth_mm), float(thickness_mm), float(slide_mm)
        if not (math.isfinite(self.thickness_mm) and self.thickness_mm > 0):
            raise ValueError(f"thickness_mm must be positive, got {thickness_mm!r}")
        if not (math.isfinite(self.depth_mm) and math.isfinite(self.slide_mm)):
            raise ValueError(f"depth_mm and slide_mm must be finite, got {depth_mm!r}, {slide_mm!r}")
        self.level = _level(level)
        self.name = (f"shear band {self.thickness_mm:g} mm at {self.depth_mm:g} mm sliding {self.slide_mm:g} mm"
                     f" + compression {100 * self.level:g}%")

    @property
    def peak_exy(self) -> float:
        """``e_xy`` inside the band, ``slide / (2 t)``."""
        return 0.5 * self.slide_mm / self.thickness_mm

    def _ramp(self, x):
        return np.clip((x - self.depth_mm) / self.thickness_mm + 0.5, 0.0, 1.0)

    def inside(self, points) -> np.ndarray:
        """True for points inside the band, (n,) bool."""
        return np.abs(as_points(points)[:, 0] - self.depth_mm) < 0.5 * self.thickness_mm

    def displacement(self, points) -> np.ndarray:
        p = as_points(points)
        s = self.level
        return np.column_stack([-s * p[:, 0], s / (1.0 - s) * p[:, 1] + self.slide_mm * (self._ramp(p[:, 0]) - 0.5)])

    def strain(self, points) -> np.ndarray:
        p = as_points(points)
        s = self.level
        exy = np.where(self.inside(p), self.peak_exy, 0.0)
        return np.column_stack([np.full(len(p), -s), np.full(len(p), s / (1.0 - s)), exy])

    def at(self, level) -> "ShearBand":
        lv = _level(level)
        f = lv / self.level if self.level > 0 else 0.0
        return ShearBand(self.depth_mm, self.thickness_mm, f * self.slide_mm, lv)

    def __repr__(self) -> str:
        return f"ShearBand({self.name})"


class Layers:
    """Bonded layers of different stiffness parallel to the probe face, compressed axially, plane stress: the axial
    strain steps at every interface (a true step, no near field).

    Closed form for layers laterally unbounded and free (no lateral force over the stack's depth ``block_mm``): the
    axial stress ``sigma`` is the same in every layer (equilibrium across the interfaces), the lateral strain
    ``e_yy`` is common to all (bonded), so with Young's moduli ``E_i``, thicknesses ``t_i`` and Poisson's ratio
    ``nu`` (plane stress, Hooke's law ``e_xx = (sigma - nu sigma_yy) / E``, ``e_yy = (sigma_yy - nu sigma) / E``):

    ``e_yy = -nu sigma T / sum(t_i E_i)``,  ``e_xx,i = ((1 - nu^2) sigma - nu E_i e_yy) / E_i``,  ``e_xy = 0``,

    ``T = sum(t_i)``; ``sigma`` is set so that the mean axial strain over ``[0, block_mm]`` is ``-level``.  Each
    layer is in uniform stress, so the field solves the elasticity equations exactly; ``u_x(0) = 0`` (the probe
    face), ``u_x`` piecewise linear in depth, ``u_y = e_yy y``.  In plane strain a nearly incompressible solid
    keeps ``e_xx`` continuous across such an interface (``e_yy`` is, and ``e_xx ~ -e_yy``), which is why this
    field is plane stress: the thickness takes the volume change.

    Parameters
    ----------
    interfaces_mm : sequence of float
        Depths of the interfaces, increasing, mm (inside ``(0, block_mm)``).
    moduli : sequence of float
        Relative Young's modulus of each layer, top first (``len(interfaces_mm) + 1`` values, > 0).
    level : float
        Mean axial compression over ``[0, block_mm]`` (fraction).
    poisson : float
        Poisson's ratio (default 0.5, incompressible).
    block_mm : float
        Depth of the stack (the last layer reaches it), mm.
    """

    def __init__(self, interfaces_mm=(15.0, 25.0), moduli=(1.0, 0.25, 1.0), level: float = 0.01, *,
                 poisson: float = 0.5, block_mm: float = 60.0):
        z = np.asarray(interfaces_mm, float).ravel()
        E = np.asarray(moduli, float).ravel()
        self.block_mm, self.poisson = float(block_mm), float(poisson)
        if E.size != z.size + 1 or not np.all(np.isfinite(E)) or np.any(E <= 0):
            raise ValueError(f"moduli must be {z.size + 1} positive numbers (one per layer), got {moduli!r}")
        if not (np.all(np.isfinite(z)) and np.all(np.diff(z) > 0) and (z.size == 0 or (z[0] > 0 and
                                                                                          z[-1] < self.block_mm))):
            raise ValueError(f"interfaces_mm must increase inside (0, {self.block_mm:g}) mm, got {interfaces_mm!r}")
        if not 0.0 <= self.poisson <= 0.5:
            raise ValueError(f"poisson must lie in [0, 0.5], got {poisson!r}")
        self.interfaces_mm, self.moduli = z, E
        self.level = _level(level)
        edges = np.r_[0.0, z, self.block_mm]
        t = np.diff(edges)
        nu = self.poisson
        # unit stress sigma = -1: strains per layer, then scaled to the mean axial strain -level
        eyy1 = nu * t.sum() / np.sum(t * E)
        exx1 = (-(1.0 - nu**2) - nu * E * eyy1) / E
        c = self.level / (np.sum(t * -exx1) / t.sum()) if self.level > 0 else 0.0
        self.exx_layers, self.eyy = c * exx1, c * eyy1
        # u_x at the top of each layer (continuous, 0 at the probe face)
        self._ux_top = np.r_[0.0, np.cumsum(self.exx_layers[:-1] * t[:-1])]
        self._tops = edges[:-1]
        self.name = (f"layers E {'/'.join(f'{e:g}' for e in E)} at {'/'.join(f'{d:g}' for d in z)} mm"
                     f" plane stress {100 * self.level:g}%")

    def layer(self, points) -> np.ndarray:
        """Index of the layer holding each point, (n,) int (depths above 0 in the first, below the stack in the last)."""
        return np.searchsorted(self.interfaces_mm, as_points(points)[:, 0], side="right")

    def displacement(self, points) -> np.ndarray:
        p = as_points(points)
        k = self.layer(p)
        ux = self._ux_top[k] + self.exx_layers[k] * (p[:, 0] - self._tops[k])
        return np.column_stack([ux, self.eyy * p[:, 1]])

    def strain(self, points) -> np.ndarray:
        p = as_points(points)
        k = self.layer(p)
        return np.column_stack([self.exx_layers[k], np.full(len(p), self.eyy), np.zeros(len(p))])

    def at(self, level) -> "Layers":
        return Layers(self.interfaces_mm, self.moduli, level, poisson=self.poisson, block_mm=self.block_mm)

    def __repr__(self) -> str:
        return f"Layers({self.name})"


class SlidingColumns:
    """Columns of different stiffness side by side, each free to slide along its vertical neighbours (frictionless
    contact), under a uniform axial pressure: a true lateral step of the axial strain.

    A bonded interface cannot carry a lateral step of ``e_xx`` (``u_x`` is continuous along a vertical interface, so
    its derivative along the interface is too); a frictionless one can.  Each column is in uniform uniaxial stress
    ``sigma_xx = sigma``, ``sigma_yy = sigma_xy = 0``: zero contact pressure and zero shear on every interface, so
    the field solves the elasticity equations exactly.  With Young's moduli ``E_i`` and Poisson's ratio ``nu``
    (Hooke's law, plane stress: ``e_xx = sigma / E``, ``e_yy = -nu sigma / E``; plane strain: ``e_xx = (1 - nu^2)
    sigma / E``, ``e_yy = -nu (1 + nu) sigma / E``):

    ``u_x = e_xx,i x`` (0 at the probe face, so the columns slip past each other by ``(e_xx,i - e_xx,i+1) x`` at
    depth ``x``),  ``u_y`` continuous, piecewise linear with slope ``e_yy,i``, 0 at ``y = 0``,  ``e_xy = 0`` away
    from the interfaces (on them the slip is a jump of ``u_x``: its shear strain is a line, not a field).

    ``sigma`` is set so that the width-weighted mean axial strain over ``[-width_mm / 2, width_mm / 2]`` is
    ``-level``.

    Parameters
    ----------
    interfaces_mm : sequence of float
        Lateral positions of the vertical interfaces, increasing, mm (inside ``(-width_mm / 2, width_mm / 2)``).
    moduli : sequence of float
        Relative Young's modulus of each column, leftmost (most negative ``y``) first (``len(interfaces_mm) + 1``
        values, > 0).
    level : float
        Mean axial compression over the width (fraction).
    model : {"plane-stress", "plane-strain"}
    poisson : float
        Poisson's ratio (default 0.5, incompressible).
    width_mm : float
        Width over which the mean strain is ``-level``, mm.
    """

    def __init__(self, interfaces_mm=(-5.0, 5.0), moduli=(1.0, 0.25, 1.0), level: float = 0.01, *,
                 model: str = "plane-stress", poisson: float = 0.5, width_mm: float = 40.0):
        z = np.asarray(interfaces_mm, float).ravel()
        E = np.asarray(moduli, float).ravel()
        self.width_mm, self.poisson = float(width_mm), float(poisson)
        if model not in ("plane-strain", "plane-stress"):
            raise ValueError(f"model must be 'plane-strain' or 'plane-stress', got {model!r}")
        self.model = model
        if E.size != z.size + 1 or not np.all(np.isfinite(E)) or np.any(E <= 0):
            raise ValueError(f"moduli must be {z.size + 1} positive numbers (one per column), got {moduli!r}")
        half = 0.5 * self.width_mm
        if not (np.all(np.isfinite(z)) and np.all(np.diff(z) > 0) and (z.size == 0 or (z[0] > -half and
                                                                                          z[-1] < half))):
            raise ValueError(f"interfaces_mm must increase inside (-{half:g}, {half:g}) mm, got {interfaces_mm!r}")
        if not 0.0 <= self.poisson <= 0.5:
            raise ValueError(f"poisson must lie in [0, 0.5], got {poisson!r}")
        self.interfaces_mm, self.moduli = z, E
        self.level = _level(level)
        nu = self.poisson
        # unit compressive stress: axial and lateral strain per column, then scaled to the mean axial strain -level
        exx1 = -(1.0 if model == "plane-stress" else 1.0 - nu**2) / E
        eyy1 = (nu if model == "plane-stress" else nu * (1.0 + nu)) / E
        t = np.diff(np.clip(np.r_[-half, z, half], -half, half))
        c = self.level / (np.sum(t * -exx1) / t.sum()) if self.level > 0 else 0.0
        self.exx_columns, self.eyy_columns = c * exx1, c * eyy1
        # u_y = G(y) - G(0), G the integral of e_yy from the first interface (continuous across every interface)
        self._G_at = np.r_[0.0, np.cumsum(self.eyy_columns[1:-1] * np.diff(z))] if z.size else np.zeros(0)
        self._uy0 = float(self._G(np.zeros(1))[0])
        self.name = (f"sliding columns E {'/'.join(f'{e:g}' for e in E)} at y {'/'.join(f'{d:g}' for d in z)} mm"
                     f" {model} {100 * self.level:g}%")

    def column(self, points) -> np.ndarray:
        """Index of the column holding each point, (n,) int."""
        return np.searchsorted(self.interfaces_mm, as_points(points)[:, 1], side="right")

    def _G(self, y) -> np.ndarray:
        z = self.interfaces_mm
        if not z.size:
            return self.eyy_columns[0] * y
        k = np.searchsorted(z, y, side="right")
        left = z[np.maximum(k - 1, 0)]
        return np.where(k == 0, 0.0, self._G_at[np.maximum(k - 1, 0)]) + self.eyy_columns[k] * (y - left)

    def displacement(self, points) -> np.ndarray:
        p = as_points(points)
        k = self.column(p)
        return np.column_stack([self.exx_columns[k] * p[:, 0], self._G(p[:, 1]) - self._uy0])

    def strain(self, points) -> np.ndarray:
        p = as_points(points)
        k = self.column(p)
        return np.column_stack([self.exx_columns[k], self.eyy_columns[k], np.zeros(len(p))])

    def at(self, level) -> "SlidingColumns":
        return SlidingColumns(self.interfaces_mm, self.moduli, level, model=self.model, poisson=self.poisson,
                              width_mm=self.width_mm)

    def __repr__(self) -> str:
        return f"SlidingColumns({self.name})"


#: The small 2D inclusion model (mm, MPa) used by :class:`Inclusion`: a 80 mm block, bottom clamped, the whole top
#: face pressed (slip), a 10 mm disk 20 mm deep, 0.4 mm P2 triangles over the imaged region.
INCLUSION_MODEL = dict(block_mm=80.0, inclusion_diameter_mm=10.0, inclusion_depth_mm=20.0, patch_mm=None,
                       mesh_size_mm=0.4, coarse_size_mm=4.0, refine_region_mm=(60.0, 30.0), bottom="fixed",
                       background_modulus=10.0, poisson=0.495)


class Inclusion:
    """A stiff or soft disk in a compressed block, plane strain or plane stress, from the FE forward model.

    One FE solve per (model, modulus) at 1 mm top-face compression (:func:`forward.elasticity.cached_solve`, disk
    cache; seconds the first time), scaled linearly to the requested level.  In the probe's frame (the top face
    is the probe), the top-face motion is subtracted: ``u = c (U_FE(x) - (1, 0))`` with ``c = level * block / 1 mm``
    so the mean axial strain of the block is ``-level``; the strain is ``c E_FE(x)``, the P2 solution's own
    gradient at the point (exact FE values).  Points outside the block give NaN.

    Parameters
    ----------
    kind : {"stiff", "soft"}
        Inclusion modulus 40 MPa (stiff, x4) or 2.5 MPa (soft, /4) in a 10 MPa background.
    model : {"plane-strain", "plane-stress"}
    level : float
        Mean axial compression of the block (fraction).
    radius_mm : float, optional
        Disk radius, mm (default: the model's 5 mm); the FE mesh over the imaged region is refined to at most a
        quarter of the radius (bonded disk, 1-8 mm: :data:`INCLUSION_MODEL` otherwise).
    """

    MODULI = {"stiff": 40.0, "soft": 2.5}

    def __init__(self, kind: str = "stiff", model: str = "plane-strain", level: float = 0.01, *,
                 radius_mm: float | None = None, _solution=None):
        if kind not in self.MODULI:
            raise ValueError(f"inclusion kind must be one of {tuple(self.MODULI)}, got {kind!r}")
        if model not in ("plane-strain", "plane-stress"):
            raise ValueError(f"inclusion model must be 'plane-strain' or 'plane-stress', got {model!r}")
        self.kind, self.model = kind, model
        self.level = _level(level)
        self.scale = self.level * INCLUSION_MODEL["block_mm"]
        params = dict(INCLUSION_MODEL)
        if radius_mm is not None:
            r = float(radius_mm)
            r_max = 0.3 * params["refine_region_mm"][1]          # the disk well inside the refined region
            if not (math.isfinite(r) and 0 < r <= r_max):
                raise ValueError(f"radius_mm must be in (0, {r_max:g}] mm, got {radius_mm!r}")
            if r != 0.5 * params["inclusion_diameter_mm"]:
                params["inclusion_diameter_mm"] = 2.0 * r
                params["mesh_size_mm"] = min(params["mesh_size_mm"], 0.25 * r)
        if _solution is None:
            from .elasticity import cached_solve

            _solution = cached_solve(model, inclusion_modulus=self.MODULI[kind], compression_mm=1.0, **params)
        self.solution = _solution
        self.centre = (params["inclusion_depth_mm"], 0.0)
        self.radius_mm = params["inclusion_diameter_mm"] / 2.0
        r_txt = "" if radius_mm is None else f" r {self.radius_mm:g} mm"
        self.name = f"{kind} inclusion{r_txt} {model} {100 * self.level:g}%"

    def displacement(self, points) -> np.ndarray:
        u = self.solution.displacement(as_points(points))
        u[:, 0] -= 1.0
        return self.scale * u

    def strain(self, points) -> np.ndarray:
        return self.scale * self.solution.strain(as_points(points))

    def inside(self, points) -> np.ndarray:
        """True for points inside the inclusion disk, (n,) bool."""
        p = as_points(points)
        return (p[:, 0] - self.centre[0]) ** 2 + (p[:, 1] - self.centre[1]) ** 2 < self.radius_mm**2

    def at(self, level) -> "Inclusion":
        r = None if self.radius_mm == 0.5 * INCLUSION_MODEL["inclusion_diameter_mm"] else self.radius_mm
        return Inclusion(self.kind, self.model, level, radius_mm=r, _solution=self.solution)

    def __repr__(self) -> str:
        return f"Inclusion({self.name})"
