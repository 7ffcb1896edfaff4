"""Displacement and strain of a bilinear-quad FE field, evaluated in one place.

Small strains ``exx = dux/dx``, ``eyy = duy/dy``, ``exy = (dux/dy + duy/dx) / 2`` (tensor shear), the quantity
of the paper's strain errors ("Results").  Every strain femreg reports comes from :func:`strain_components`:
at located points (:func:`sample`, used for pixel grids and arbitrary points), at element centres
(:func:`element_strains`, for meshes and ParaView) and at quadrature points (:mod:`femreg.metrics`).

The gradient of a bilinear field is discontinuous across element edges (axial strain constant along x in each
element: a blocky image, first-order accurate).  What femreg reports by default is the *recovered* strain
(:func:`recovered_strains`): a bilinear field interpolated like the displacement.  Four recoveries:

* ``"adaptive"`` (default): the average below blended with the projection below (consistent mass only, held
  within the element strains around each node) by how little the registration's element strains scatter about
  their own average (:func:`strain_roughness`): the projection where they are clean (high-frequency probes, sharp
  inclusion edges kept), the average where they are noisy (the projection would show the noise); per result, one
  weight.
* ``"average"``: the element-centre strains -- the superconvergent points of bilinear quads -- averaged
  at each node (O. C. Zienkiewicz, J. Z. Zhu, Int. J. Numer. Meth. Eng. 24:337-357, 1987, "simple averaging"; on a
  uniform tensor mesh the same nodal values as their 1992 superconvergent patch recovery with a linear patch
  polynomial at interior nodes).  It blurs a sharp edge over about two elements.
* ``"projection"``: the L2 projection of the element-centre strains onto the bilinear space, its mass matrix
  blended 3/4 consistent + 1/4 lumped (E. Hinton, J. S. Campbell, Int. J. Numer. Meth. Eng. 8:461-480, 1974,
  "global smoothing"; with the lumped mass alone it is the average).  Sharper edges, less smoothing of noise
  and defects (numbers in :func:`recovered_strains`).
* ``"edge"``: edge-aware (:func:`edge_aware_strains`): per element, each corner averages only the elements around
  the node that continue this element's trend, so a strain step stays a step; per-element corner values (4, n_el,
  3), bilinear within each element, continuous (the average) wherever no step stands out.  Opt-in: sharper
  inclusion edges, but it also keeps the element-scale defects of a registration (numbers in
  :func:`recovered_strains`).

All are exact for affine fields.  ``strain="element"`` keeps the raw element gradient.
Lengths in mm; ``u`` is the interleaved nodal vector ``[ux0, uy0, ux1, ...]`` (scikit-fem's vector DOF order).
"""
from __future__ import annotations

import functools
import warnings

import numpy as np
import scipy.sparse as sp

from . import mesh as _mesh
from .errors import InputError
from .mesh import check_mesh
from .quadrature import ELEMENT_CENTRE_RULE

__all__ = ["FIELDS", "STRAIN_MODES", "strain_components", "sample", "element_strains", "nodal_average",
           "edge_aware_strains", "edge_aware_corners", "location_corners", "graded_weights",
           "recovered_strains", "projected_strains", "adaptive_strains", "adaptive_weight", "strain_roughness",
           "ROUGHNESS_SHARP", "ROUGHNESS_SMOOTH", "check_strain_mode", "element_strain_operator",
           "RECOVERY_METHODS", "DEFAULT_RECOVERY", "centre_gradient_operators", "inner_elements", "lateral_ratio",
           "quadrant_ratios"]

#: Names of the sampled fields, in order.
FIELDS = ("ux", "uy", "exx", "eyy", "exy")
#: How strains are evaluated: "recovered" (continuous, default) or "element" (the raw element gradient).
STRAIN_MODES = ("recovered", "element")
#: How the recovered strain is computed (module docstring); the first is the default.
RECOVERY_METHODS = ("adaptive", "average", "projection", "edge")
DEFAULT_RECOVERY = RECOVERY_METHODS[0]
#: Roughness of the element-centre strains (:func:`strain_roughness`) at or below which the adaptive recovery is
#: the full L2 projection, and at or above which it is the nodal average (linear between).  The middle of where
#: each was best on 37 simulated pairs (robustness seed 0, inclusion sizes, the plane-strain model's pairs): the
#: projection (consistent weight 1) lowest on every pair of roughness <= 0.004, the average or a quarter of the
#: projection on every pair of roughness >= 0.013 (numbers in :func:`recovered_strains`).
ROUGHNESS_SHARP, ROUGHNESS_SMOOTH = 0.006, 0.016
#: Weight of the consistent mass in the projection's mass matrix (the rest lumped; 0 is the nodal average).  More
#: sharpens edges more and amplifies local defects more: on a pair whose peak-hopping islands were repaired the
#: total strain error is 15.0 % (average), 18.5 % (3/4), 21.0 % (1); on the robustness benchmark's inclusions 1
#: gains another 0.2-0.3 points over 3/4 and raises the smooth bending pair by 0.15 over the average.
PROJECTION_CONSISTENT_WEIGHT = 0.75


def check_strain_mode(strain: str) -> str:
    """``strain`` if it is one of :data:`STRAIN_MODES`, else InputError."""
    if strain not in STRAIN_MODES:
        raise InputError(f"strain must be one of {STRAIN_MODES}, got {strain!r}")
    return strain


def strain_components(grad) -> np.ndarray:
    """[exx, eyy, exy] from a displacement gradient ``grad[i, j] = du_i/dx_j`` of shape (2, 2, ...);
    returns shape (..., 3)."""
    g = np.asarray(grad, float)
    return np.stack([g[0, 0], g[1, 1], 0.5 * (g[0, 1] + g[1, 0])], axis=-1)


def sample(u, location, fields=FIELDS, nodal_strain=None, mesh_cells=None) -> dict:
    """Fields of the nodal displacement ``u`` at located points.

    Parameters
    ----------
    u : (2 n_nodes,) mm
    location : femreg.pixels.Location
        Points inside the mesh with their element nodes ``nodes`` (m, 4), shape functions ``N`` (m, 4) and
        physical gradients ``dN`` (m, 4, 2) per mm.
    fields : names from :data:`FIELDS`
    nodal_strain : (n_nodes, 3), (4, n_el, 3) or None
        Recovered strains [exx, eyy, exy] (:func:`recovered_strains`) to interpolate bilinearly: nodal values, or
        per-element corner values in ``mesh_cells`` (4, n_el) order (the ``"edge"`` recovery); None takes the
        element gradient of ``u``.

    Returns
    -------
    dict name -> (m,) float: values at the located (inside) points, in ``location``'s order.
    """
    u = np.asarray(u, float)
    ux, uy = u[0::2][location.nodes], u[1::2][location.nodes]
    out = {}
    if "ux" in fields:
        out["ux"] = np.sum(location.N * ux, axis=1)
    if "uy" in fields:
        out["uy"] = np.sum(location.N * uy, axis=1)
    if any(f in fields for f in ("exx", "eyy", "exy")):
        if nodal_strain is not None and np.ndim(nodal_strain) == 3:
            if mesh_cells is None:
                raise InputError("per-element corner strains (4, n_el, 3) need the mesh cells")
            e = np.einsum("mc,mck->mk", location.N, location_corners(location, nodal_strain, mesh_cells))
        elif nodal_strain is not None:
            ns = np.asarray(nodal_strain, float)
            e = np.stack([np.sum(location.N * ns[:, k][location.nodes], axis=1) for k in range(3)], axis=-1)
        else:
            grad = np.stack([np.einsum("nk,nkd->dn", ux, location.dN),
                             np.einsum("nk,nkd->dn", uy, location.dN)])
            e = strain_components(grad)
        for k, name in enumerate(("exx", "eyy", "exy")):
            if name in fields:
                out[name] = e[:, k]
    return out


def location_corners(location, corner_values, mesh_cells) -> np.ndarray:
    """Per-element corner values (4, n_el, k) in ``mesh_cells`` (4, n_el) order, at each located point's element
    and in the order of its ``location.nodes`` (which need not be the cell order): shape (m, 4, k)."""
    cv = np.asarray(corner_values, float)
    el, nodes = location.element, location.nodes
    cells = np.asarray(mesh_cells)
    pos = np.argmax(nodes[:, :, None] == cells[:, el].T[:, None, :], axis=2)       # (m, 4) cell-order corner
    return cv[pos, el[:, None]]


def element_strains(mesh_points, mesh_cells, u) -> np.ndarray:
    """Small strains [exx, eyy, exy] at each bilinear quad's centre (reference point (1/2, 1/2)), shape (n_el, 3).

    Exact for a displacement field affine in (x, y).  ``mesh_points`` (2, n_nodes) mm, ``mesh_cells`` (4, n_el).
    """
    from skfem import Basis, ElementQuad1, ElementVector, MeshQuad1

    p, t, uu = check_mesh(mesh_points, mesh_cells, u)
    try:
        basis = Basis(MeshQuad1(p, t), ElementVector(ElementQuad1()), quadrature=ELEMENT_CENTRE_RULE)
    except Exception as exc:  # noqa: BLE001  scikit-fem raises a bare Exception for a zero Jacobian
        raise InputError(f"mesh has degenerate (zero-area) quads ({exc})") from None
    return strain_components(np.asarray(basis.interpolate(uu).grad)[:, :, :, 0])


def nodal_average(mesh_cells, cell_values, n_nodes, cell_weights=None) -> np.ndarray:
    """Average of the values of the cells around each node: (n_el, k) -> (n_nodes, k); ``mesh_cells`` (4, n_el)
    as everywhere in femreg (scikit-fem's ``mesh.t``).  ``cell_weights`` (n_el,) weights each cell's value
    (None: all equal, femreg's recoveries; :func:`graded_weights`: exact for a linear field on a graded mesh)."""
    t = np.asarray(mesh_cells)
    if t.ndim != 2 or t.shape[1] != np.shape(cell_values)[0]:
        raise InputError(f"mesh_cells must be (4, n_el) with n_el = {np.shape(cell_values)[0]}, got {t.shape}")
    v = np.asarray(cell_values, dtype=float)
    v2 = v.reshape(v.shape[0], -1)
    out = np.zeros((n_nodes, v2.shape[1]))
    cw = np.ones(t.shape[1]) if cell_weights is None else np.asarray(cell_weights, float)
    if cw.shape != (t.shape[1],) or not np.all(np.isfinite(cw) & (cw > 0)):
        raise InputError(f"cell_weights must be {t.shape[1]} positive finite values, got shape {cw.shape}")
    count = np.bincount(t.ravel(), weights=np.tile(cw, t.shape[0]), minlength=n_nodes)
    for k in range(v2.shape[1]):
        out[:, k] = np.bincount(t.ravel(), weights=np.tile(cw * v2[:, k], t.shape[0]), minlength=n_nodes)
    with np.errstate(invalid="ignore", divide="ignore"):
        out /= count[:, None]
    return out.reshape((n_nodes,) + v.shape[1:])


def graded_weights(mesh_points, mesh_cells) -> np.ndarray:
    """Weights (n_el,) for a nodal average of element-centre strains (:func:`nodal_average`): 1 / element area,
    scaled to at most 1.

    At an interior node of a tensor mesh the four element centres lie at half their element's width and height
    from it; weighting each by ``1 / (h_x h_y)`` makes the average the bilinear interpolation of the four centre
    values at the node, exact for a strain linear in x and y.  The plain average (equal weights) is exact only
    where the two sizes agree: where a graded mesh changes element size it is off by ``g (h_2 - h_1) / 4`` (``g``
    the strain gradient), a kink at every change of size that the picture shows as steps along the refined rows
    and columns.  Uniform meshes: equal weights, the plain average exactly.  ``mesh_points`` (2, n_nodes) mm,
    ``mesh_cells`` (4, n_el).

    Not what femreg's recoveries use (they weight equally), measured (``benchmarks/exy_staircase.py``, defaults,
    the same registrations recovered both ways):

    * the kink is real but small beside what a registration's picture carries: on a linear e_xy over 1 mm /
      0.25 mm rows the equal weights' nodal error is 1.6 % of the strain's range at the size changes (these: 0);
      e_xy of a refined inclusion's registration away from the rim is 1.3-7.4 x as rough (RMS second
      differences along x and y) as the truth, the exact displacement on the same mesh recovered alike 0.45-1.9 x:
      the steps a user sees are the registration's element strains, not the recovery, the sampling or the plot;
      these weights change that roughness by at most 4 % (r 8 mm: 2.98 / 7.41 -> 2.92 / 7.16);
    * total strain error: robustness, inclusion and band pairs change by -0.07 to +0.07 points, except
      the 3 mm band under L3 (``held_band3_s0.4_d12_L3``): 28.36 -> 28.52 % (exact displacement 19.28 -> 19.54 %):
      where a band's face lies on a change of size the heavier fine element moves the nodal value at the face
      towards the inside of the band.
    """
    c = np.asarray(mesh_points, float)[:, np.asarray(mesh_cells)]            # (2, 4, n_el)
    # shoelace area of each quad (corners in cell order, counter-clockwise or not)
    area = 0.5 * np.abs(np.sum(c[0] * np.roll(c[1], -1, axis=0) - np.roll(c[0], -1, axis=0) * c[1], axis=0))
    with np.errstate(divide="ignore"):
        w = 1.0 / area
    # a degenerate quad is refused by element_strains before this matters; keep the weights finite regardless
    return np.where(np.isfinite(w), w / np.max(w[np.isfinite(w)], initial=1.0), 1.0)


def recovered_strains(mesh_points, mesh_cells, u, method: str = DEFAULT_RECOVERY) -> np.ndarray:
    """Recovered strains [exx, eyy, exy], shape (n_nodes, 3) (``"edge"``: (4, n_el, 3)), interpolated bilinearly.

    ``method="adaptive"`` (default): see the end.  ``"average"``: the mean of the element-centre strains
    (:func:`element_strains`) of the elements around each node (Zienkiewicz & Zhu 1987, simple averaging).
    ``"projection"``: :func:`projected_strains`.

    Measured, projection against average (R_P_sigma defaults; ``benchmarks/recovery.py``):

    * robustness benchmark, 17 pairs (the sequence left out), total strain error: lower on the 8 inclusion pairs by
      0.5-0.7 points (e.g. stiff plane-stress 4 % 10.05 -> 9.34 %; the element strain 10.57 %), within +0.07 on
      the 9 others (bending 5.76 -> 5.83 %); the half-contrast contour of the inclusions' axial strain 0.047 R RMS
      from the true contour against 0.052 R (element strain 0.063 R); on an exact FE inclusion interpolated on a
      mesh of radius / element 2: 0.081 R against 0.110 R;
    * the paper's study, single frame 1 -> 7 (2 mm mesh): exact truth 0.0-0.5 points lower on all six data sets,
      but in the paper's convention (truth interpolated at the nodes, both recovered alike) 0.3-0.5 points higher;
    * a pair whose peak-hopping islands were repaired (3 MHz, 1 degree): 15.0 -> 18.5 % (the sharper recovery
      shows the residual defects more).

    So the average stays the default; the projection is there for pictures of sharp-edged inclusions.

    ``"edge"``: :func:`edge_aware_strains`, returned as per-element corner values (4, n_el, 3) in ``mesh_cells``
    order (every sampler here takes either shape).  Measured against the average on the same registrations
    (defaults; ``benchmarks/recovery.py``, seeds 0 and 7 for the robustness pairs):

    * inclusions (``--suite inclusions``): the exact displacement on the refined mesh (the floor) 0.16-0.44 points
      lower on all 8 pairs (r 8 mm 8.33 -> 7.97 %; the element-centre strain 7.68 %), its axial edge at r 3 mm
      1.39 / 1.27 -> 1.23 / 1.15 mm (1 % / 4 %); the registrations 0.03-0.22 points lower on all 8 (r 8 mm
      10.52 -> 10.50 %), the r 3 mm axial edge 1.41 / 1.25 -> 1.34 / 1.23 mm; CNR_e within -0.9 / +2.5 except
      r 2 mm under L3 (47.2 -> 40.7);
    * robustness pairs (seeds 0 / 7): within 0.02 on the uniform ones and bending, 0.05-0.28 lower on the
      plane-strain inclusions and the 1 % plane-stress ones, +0.08 to +0.25 on the 4 % plane-stress ones (soft
      7.92 -> 8.17 %): the sharper recovery keeps element-scale blocks of their shear strain;
    * shear bands: 9 of 11 lower by 0.8-9.5 points (band 2 mm, 0.3 mm slide 22.0 -> 12.5 %), but +1.1 on the
      0.5 mm band the registration does not resolve and +2.4 on the 3 mm band under L3 (rows of unequal e_xy
      inside the band stay as steps); the slide (integral of e_xy across the band) is off by more on 9 of 11
      (band 1 mm at 8 mm depth -4.7 -> -13.1 %): the one-sided corners do not keep the integral; the band's
      upper face (10-90 %) sharper on all 11 (band 2 mm 0.59 -> 0.25 mm, ``shear_bands.py``);
    * pictures: on the in vivo pair (seq299 frames 1 -> 2) the mean absolute second difference of e_xx at 0.3 mm axial
      steps is 0.029 / 0.0048 % (axial / lateral) against 0.021 / 0.0041 % (average) and 0.042 / 0.0082 %
      (element strain): rougher than the average, about 40 % of the way to the element strain.

    So it is an option, for pictures of sharp-edged inclusions.

    ``"adaptive"`` (:func:`adaptive_strains`): the projection (consistent weight 1) where the element strains are
    clean, the average where they scatter, by their :func:`strain_roughness`.  This function decides on the
    roughness alone; a registration result (:attr:`femreg.registration.RegistrationResult.recovery_weight`) also
    keeps the average where its refinement split nothing (no sharp feature to keep) or found a slip along the beam.
    Measured against the average on the same registrations (defaults; total strain error, points):

    * which weight is best depends on the roughness: on 37 pairs (robustness seed 0, inclusion sizes, the
      plane-strain model's 11) the projection was best on every pair of roughness <= 0.004 (0.2-0.7 lower), the
      average or a quarter of the projection on every pair of roughness >= 0.013 (the full projection 0.1-1.6
      worse: bending 3.81 -> 5.44 %), mixed between (0.005-0.012);
    * the projection rings at a step (about 5-15 % of it either side: thin false stripes beside a shear band or
      along a layer's interface), so it is held within the element strains around each node (no value that no
      element measured; :func:`adaptive_strains`);
    * the plane-strain model's 11 held-out inclusions: 7 lower by 0.01-0.58 (15 MHz stiff plane stress 8.38 ->
      7.80 %, 7.5 MHz 15 dB r 8 mm 8.24 -> 7.85 %), 3 identical, 1 higher (7.5 MHz soft plane stress 1 % 6.62 ->
      6.65); robustness seeds 0 / 7: 5 refined inclusions lower by 0.01-0.64, stiff plane stress 4 % under the
      paper's probe +0.15 / +0.03 (roughness 0.010), the 8 % compression pair +0.07, every other pair identical;
      inclusion sizes 0.0-0.2 lower, 3 MHz r 2 mm +0.1; layers: 8 of 13 lower by 0.2-0.7 (soft 1 % paper 7.6 ->
      6.9 %, its 10-90 % edge 0.85 -> 0.73 mm), 3 identical, 2 higher by 0.1; shear bands: 9 of 11 lower by
      0.9-8.8, the 1 mm band at 8 mm depth under L7 its peak e_xy 0.77 -> 1.04 of the truth, the 0.5 mm band
      +0.1; sliding columns, rotated and heterogeneous pairs identical (not split, or a slip found);
    * held out (none used to set the rule): the 114 registrations of ``benchmarks/inversion.py``'s seven sets
      (inclusions of contrast 0.25-4, radius 4-8 mm, 3-15 MHz, 15-30 dB, both models; error over the mesh, exact
      truth): 63 lower by 0.01-0.32, 36 identical, 15 higher by at most 0.10, median change -0.03.

    ``mesh_points`` (2, n_nodes) mm, ``mesh_cells`` (4, n_el), ``u`` (2 n_nodes,) mm.
    """
    if method not in RECOVERY_METHODS:
        raise InputError(f"recovery method must be one of {RECOVERY_METHODS}, got {method!r}")
    uu = np.asarray(u, float)
    if method == "adaptive":
        return adaptive_strains(mesh_points, mesh_cells, uu)
    if method == "projection" and np.all(np.isfinite(uu)):
        return projected_strains(mesh_points, mesh_cells, uu)
    if method == "edge":
        return edge_aware_strains(mesh_points, mesh_cells, uu)
    # the average is local: a non-finite displacement spoils only its own neighbourhood
    e = element_strains(mesh_points, mesh_cells, uu)
    return nodal_average(mesh_cells, e, np.asarray(mesh_points).shape[1])


def strain_roughness(mesh_points, mesh_cells, u) -> float:
    """How much the element-centre strains scatter about their own nodal average, relative to the strain: a
    noise-to-signal ratio of a registration's strain, without a truth.

    ``r_e = |e_e - mean_corners(a)|`` per element (:func:`element_strains` ``e``, its nodal average ``a``
    (:func:`nodal_average`) at the element's four corners; the norm over [exx, eyy, exy]), returned as
    ``median(r) / sqrt(median(exx^2 + eyy^2))``.  Zero for affine fields; a sharp edge touches few elements and
    leaves the median alone; noise and element-scale defects raise it.  NaN where the strain is zero or ``u`` not
    finite.  Measured on registrations with the defaults: 0.002-0.004 at 12-15 MHz, 0.005-0.011 at 7.5 MHz,
    0.010-0.021 under the paper's probe (5 MHz, 0.3 mm pitch) and 3 MHz, 0.030 on the bending pair.
    ``mesh_points`` (2, n_nodes) mm, ``mesh_cells`` (4, n_el), ``u`` (2 n_nodes,) mm.
    """
    uu = np.asarray(u, float)
    if not np.all(np.isfinite(uu)):
        return float("nan")
    e = element_strains(mesh_points, mesh_cells, uu)
    t = np.asarray(mesh_cells)
    return _roughness(e, t, nodal_average(t, e, np.asarray(mesh_points).shape[1]))


def _roughness(e, t, avg) -> float:
    """:func:`strain_roughness` of the element-centre strains ``e`` (n_el, 3) and their nodal average ``avg``."""
    scale = float(np.sqrt(np.median(np.sum(e[:, :2] ** 2, axis=1))))
    if not scale > 0.0:
        return float("nan")
    return float(np.median(np.linalg.norm(e - avg[t].mean(axis=0), axis=1)) / scale)


def adaptive_weight(roughness: float) -> float:
    """Weight of the projection in the adaptive recovery: 1 at roughness <= :data:`ROUGHNESS_SHARP`, 0 at >=
    :data:`ROUGHNESS_SMOOTH` or NaN, linear between."""
    if not np.isfinite(roughness):
        return 0.0
    return float(np.clip((ROUGHNESS_SMOOTH - roughness) / (ROUGHNESS_SMOOTH - ROUGHNESS_SHARP), 0.0, 1.0))


def adaptive_strains(mesh_points, mesh_cells, u, weight: float | None = None, cell_weights=None) -> np.ndarray:
    """The default recovery: ``(1 - w) average + w projection``, shape (n_nodes, 3) [exx, eyy, exy].

    ``average`` the nodal average (:func:`nodal_average` of :func:`element_strains`), ``projection`` the plain L2
    projection (:func:`projected_strains` with consistent weight 1) held, per node and component, within the
    element-centre strains of the elements around the node (a bound-preserving limit: the projection's ringing at
    a step leaves no false stripes), ``w`` the :func:`adaptive_weight` of the field's :func:`strain_roughness` (or
    ``weight`` given).  ``w = 0`` is the nodal average exactly.  Exact for affine fields (both are).
    ``mesh_points`` (2, n_nodes) mm, ``mesh_cells`` (4, n_el), ``u`` (2 n_nodes,) mm; ``cell_weights``: the nodal
    average's (:func:`nodal_average`; e.g. :func:`graded_weights`), None the equal weights of the default.
    """
    if weight is not None and not 0.0 <= float(weight) <= 1.0:
        raise InputError(f"weight must lie in [0, 1], got {weight!r}")
    e = element_strains(mesh_points, mesh_cells, u)                   # validates the mesh and u
    t = np.asarray(mesh_cells)
    n = np.asarray(mesh_points).shape[1]
    avg = nodal_average(t, e, n, cell_weights)
    w = adaptive_weight(_roughness(e, t, avg)) if weight is None else float(weight)
    if w == 0.0:
        return avg
    # the projection rings at a step (up to about 15 % of it, either side); held within the range of the
    # element strains around each node it keeps the step's sharpness without new extrema
    lo, hi = np.full((n, 3), np.inf), np.full((n, 3), -np.inf)
    for k in range(t.shape[0]):
        np.minimum.at(lo, t[k], e)
        np.maximum.at(hi, t[k], e)
    return (1.0 - w) * avg + w * np.clip(_project(mesh_points, mesh_cells, e, 1.0), lo, hi)


def projected_strains(mesh_points, mesh_cells, u, consistent_weight: float | None = None) -> np.ndarray:
    """L2 projection of the element-centre strain onto the bilinear nodal space, shape (n_nodes, 3)
    [exx, eyy, exy].

    Solves ``M_w s_k = b_k`` with ``b_k,i = sum_e e_k,e int_e N_i dx`` (``e_k,e`` the strain at element e's centre,
    :func:`element_strains`: the superconvergent value, without the element's hourglass variation) and
    ``M_w = w M + (1 - w) diag(M 1)``, ``M`` the consistent mass matrix of ``ElementQuad1`` (scikit-fem assembly,
    2 x 2 Gauss, exact), ``w = consistent_weight`` (default :data:`PROJECTION_CONSISTENT_WEIGHT`).  ``w = 0`` is
    exactly the area-weighted nodal average (on a uniform mesh :func:`nodal_average`); ``w = 1`` the plain L2
    projection (Hinton & Campbell 1974), sharpest and least smooth.  Exact for affine ``u``.
    ``mesh_points`` (2, n_nodes) mm, ``mesh_cells`` (4, n_el), ``u`` (2 n_nodes,) mm.
    """
    w = PROJECTION_CONSISTENT_WEIGHT if consistent_weight is None else float(consistent_weight)
    if not 0.0 <= w <= 1.0:
        raise InputError(f"consistent_weight must lie in [0, 1], got {consistent_weight!r}")
    e = element_strains(mesh_points, mesh_cells, u)                   # validates the mesh and u
    return _project(mesh_points, mesh_cells, e, w)


def _project(mesh_points, mesh_cells, e, w: float) -> np.ndarray:
    """:func:`projected_strains` of the element-centre strains ``e`` (n_el, 3), consistent weight ``w``."""
    import scipy.sparse as sps
    from scipy.sparse.linalg import splu
    from skfem import Basis, BilinearForm, ElementQuad1, LinearForm, MeshQuad1

    basis = Basis(MeshQuad1(np.asarray(mesh_points, float), np.asarray(mesh_cells, np.int64)), ElementQuad1(),
                  intorder=2)
    M = BilinearForm(lambda a, b, _: a * b).assemble(basis)
    lumped = sps.diags(np.asarray(M.sum(axis=1)).ravel())
    lu = splu((w * M + (1.0 - w) * lumped).tocsc())
    rhs = LinearForm(lambda v, q: q["e"] * v)
    n_qp = basis.X.shape[1]
    return np.column_stack([lu.solve(rhs.assemble(basis, e=np.repeat(e[:, k:k + 1], n_qp, axis=1)))
                            for k in range(3)])


#: Edge-aware recovery ("edge", :func:`edge_aware_strains`): a neighbour's strain is taken at a corner while its
#: misfit to the element's own linear trend is under ``EDGE_LOW`` x the tolerance, left out above ``EDGE_HIGH`` x
#: it (linear in between); the tolerance is ``EDGE_SLOPE`` x the trend's own change over that distance plus
#: ``EDGE_NOISE`` x the median over the elements of each one's largest misfit (a robust scale of noise and
#: curvature, per component).
EDGE_LOW, EDGE_HIGH, EDGE_SLOPE, EDGE_NOISE = 1.0, 2.0, 2.0, 2.0
#: Passes of averaging each edge's weight with the parallel edges of its two neighbours along it.  Measured
#: instead: none (registered r 3 mm axial edge at 1 % 1.07 against 1.34 mm, but teeth along steps, the inclusions'
#: floor 0.1-0.3 points higher, +0.32 points on the worst robustness pair); the median of the three (1.11 mm, fewer
#: teeth, but r 8 mm +0.06 and the worst robustness pair +0.31 points, the 3 mm L3 band +2.8).
EDGE_TANGENTIAL = 1


def _edge_neighbours(t):
    """Across-edge neighbours of a conforming quad mesh ``t`` (4, n_el): ``nb[k, e]`` the element across element
    e's edge k (nodes t[k], t[k+1 mod 4]), -1 on the boundary, and ``kn[k, e]`` that edge's index in it."""
    n_el = t.shape[1]
    a, b = t, np.roll(t, -1, axis=0)
    key = np.minimum(a, b).astype(np.int64) * (int(t.max()) + 1) + np.maximum(a, b)
    flat = key.ravel()                                   # half-edge h = k * n_el + e
    order = np.argsort(flat, kind="stable")
    s = flat[order]
    same = s[1:] == s[:-1]
    nb_h = np.full(flat.size, -1, np.int64)
    nb_h[order[1:][same]] = order[:-1][same]
    nb_h[order[:-1][same]] = order[1:][same]
    nb = np.where(nb_h >= 0, nb_h % n_el, -1).reshape(4, n_el)
    kn = np.where(nb_h >= 0, nb_h // n_el, -1).reshape(4, n_el)
    return nb, kn


def edge_aware_strains(mesh_points, mesh_cells, u, low: float = EDGE_LOW, high: float = EDGE_HIGH,
                       slope: float = EDGE_SLOPE, noise: float = EDGE_NOISE,
                       tangential: int = EDGE_TANGENTIAL) -> np.ndarray:
    """Edge-aware recovered strains: per element, its four corner values [exx, eyy, exy], shape (4, n_el, 3) in
    ``mesh_cells`` order, to be interpolated bilinearly within the element (:func:`sample`).

    Each corner's value is the weighted mean of the element-centre strains (:func:`element_strains`) of the
    elements around that node that continue this element's own trend, per component (an essentially
    non-oscillatory choice of stencil: A. Harten, B. Engquist, S. Osher, S. Chakravarthy, J. Comput. Phys.
    71:231-303, 1987, applied to the nodal average of Zienkiewicz & Zhu 1987):

    1. element E's view of its neighbour F across an edge: the misfit ``m = |e_F - (e_E + s d)|`` of F to the line
       through E's neighbour behind it (across E's opposite edge) and E, ``s`` that line's slope, ``d`` the centre
       distance E-F (without a neighbour behind E: ``|e_F - e_E|``, the trend taken from F's side);
    2. tolerance ``slope |s d| + noise M``, ``M`` the median over the elements of each one's largest misfit (a
       robust scale of noise and curvature): a steep trend allows a larger misfit; E's weight of F is 1 below
       ``low`` x the tolerance, 0 above ``high`` x it, linear between.  The weights need not be symmetric: the
       flat side of a step leaves out the element cut by the step, the cut element (on a trend through both
       sides) keeps both;
    3. an element left out by more than two of its neighbours is an outlier (noise, not one side of a step): its
       neighbours and it take each other in again, by ``clip(n_left_out - 2, 0, 1)``, so noise draws no squares;
       then each weight is averaged with those of the parallel edges of the two neighbours along its edge
       (``tangential`` passes): a step along a line is judged along the line, and a judgement that flips from edge
       to edge leaves no teeth;
    4. weight of an element around the node: 1 for E, its weight for an edge neighbour, the product along the path
       for the diagonal one (the larger of its two paths).

    ``low``, ``high``, ``slope``, ``noise``, ``tangential``: :data:`EDGE_LOW` ... :data:`EDGE_TANGENTIAL`.

    Where every weight is 1 (smooth fields) this is the nodal average (:func:`nodal_average`) exactly; it is exact
    for affine fields and, on both sides, for a strain step along element edges (piecewise-affine displacement).
    Deterministic, vectorised; ``mesh_points`` (2, n_nodes) mm, ``mesh_cells`` (4, n_el), ``u`` (2 n_nodes,) mm.
    """
    return edge_aware_corners(mesh_points, mesh_cells, element_strains(mesh_points, mesh_cells, u), low=low,
                              high=high, slope=slope, noise=noise, tangential=tangential)


def edge_aware_corners(mesh_points, mesh_cells, values, low: float = EDGE_LOW, high: float = EDGE_HIGH,
                       slope: float = EDGE_SLOPE, noise: float = EDGE_NOISE,
                       tangential: int = EDGE_TANGENTIAL) -> np.ndarray:
    """The corner values of :func:`edge_aware_strains` from element-centre values ``values`` (n_el, k) (each column
    on its own): shape (4, n_el, k) in ``mesh_cells`` (4, n_el) order; ``mesh_points`` (2, n_nodes) mm."""
    p = np.asarray(mesh_points, float)
    t = np.asarray(mesh_cells, np.int64)
    e = np.asarray(values, float)
    if t.ndim != 2 or t.shape[0] != 4 or e.ndim != 2 or e.shape[0] != t.shape[1]:
        raise InputError(f"values must be (n_el, k) with n_el = {t.shape[-1]} and mesh_cells (4, n_el), got "
                         f"{e.shape} and {t.shape}")
    n_el, nk = t.shape[1], e.shape[1]
    nb, kn = _edge_neighbours(t)
    cen = p[:, t].mean(axis=1)                                            # (2, n_el)
    opp = (np.arange(4)[:, None] + 2) % 4                                 # opposite local edge
    E = np.broadcast_to(np.arange(n_el), (4, n_el))
    has = nb >= 0
    F = np.where(has, nb, 0)
    Eb = nb[opp, E]                                                       # behind E
    Fb = np.where(has, nb[(np.where(has, kn, 0) + 2) % 4, F], -1)         # behind F

    def dist(A, B):
        return np.linalg.norm(cen[:, A] - cen[:, np.where(B >= 0, B, 0)], axis=0)

    d = dist(E, F)
    with np.errstate(invalid="ignore", divide="ignore"):
        trend = (e[E] - e[np.where(Eb >= 0, Eb, 0)]) * (d / dist(E, Eb))[..., None]       # s d, (4, n_el, k)
        back = (e[np.where(Fb >= 0, Fb, 0)] - e[F]) * (d / dist(F, Fb))[..., None]
    own = (Eb >= 0)[..., None]
    m = np.where(own, np.abs(e[F] - e[E] - trend), np.abs(e[F] - e[E]))
    step = np.where(own, np.abs(trend), np.where((Fb >= 0)[..., None], np.abs(back), np.inf))
    m = np.where(has[..., None], m, np.nan)
    with np.errstate(invalid="ignore"):
        # each element's largest misfit, its median over the elements: a field varying along one axis only has
        # zero misfits across half the edges, which would make the median of all misfits zero
        with warnings.catch_warnings():     # all-NaN columns (NaN strains) give NaN, handled below
            warnings.simplefilter("ignore", RuntimeWarning)
            scale = np.nanmedian(np.nanmax(m, axis=0), axis=0) if has.any() else np.zeros(nk)
    scale = np.maximum(np.nan_to_num(scale), 1e-9 * np.nanmax(np.abs(e), axis=0, initial=0.0) + 1e-300)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = m / (slope * step + noise * scale)
    c = np.clip((high - rho) / (high - low), 0.0, 1.0)
    c = np.where(np.isnan(c), 1.0, c)                                     # no trend to judge by, or NaN strains
    c = np.where(has[..., None], c, 0.0)                                  # no element there: no weight
    # 3. outliers: E's neighbours' weights of E (their edge kn towards E), taken in again before the averaging
    # along edges spreads their exclusion
    rev = np.where(has[..., None], c[np.where(has, kn, 0), F], 1.0)
    iso = np.clip((1.0 - rev).sum(axis=0) - 2.0, 0.0, 1.0)                # (n_el, k)
    c = np.where(has[..., None], np.maximum(c, np.maximum(iso[None], iso[F])), 0.0)
    for _ in range(int(tangential)):
        # mean with the parallel edges of the two neighbours along the edge: a step along a line is judged along
        # the line, not edge by edge (which leaves teeth where the judgement flips)
        acc, cnt = c.copy(), np.ones(c.shape[:2])
        for side, turn in ((1, 1), (-1, -1)):
            ks = (np.arange(4)[:, None] + side) % 4                        # E's edge towards that neighbour
            G = nb[ks, E]
            ok = (G >= 0) & has
            Gs = np.where(ok, G, 0)
            kp = (np.where(ok, kn[ks, E], 0) + turn) % 4                   # G's edge parallel to E's edge k
            ok &= nb[kp, Gs] >= 0
            acc += np.where(ok[..., None], c[kp, Gs], 0.0)
            cnt += ok
        c = np.where(has[..., None], acc / cnt[..., None], 0.0)

    # 4. per corner j of E: edges j and j-1 meet there; their neighbours F1, F2 and the diagonals behind them
    def other_edge(Fn, k_shared, node):
        """Index of Fn's other edge at ``node`` (its shared edge with E is k_shared)."""
        start = t[k_shared, Fn] == node
        return np.where(start, (k_shared - 1) % 4, (k_shared + 1) % 4)

    node = t                                                              # (4 corners, n_el)
    out = np.empty((4, n_el, nk))
    for j in range(4):
        k1, k2 = j, (j - 1) % 4
        acc = e.copy()
        wsum = np.ones((n_el, nk))
        paths = []
        for k in (k1, k2):
            Fk = nb[k]
            ok = Fk >= 0
            Fks = np.where(ok, Fk, 0)
            wF = c[k]                                                      # (n_el, k), 0 where no neighbour
            acc += wF * np.nan_to_num(e[Fks])
            wsum += wF
            ko = other_edge(Fks, np.where(ok, kn[k], 0), node[j])
            D = np.where(ok, nb[ko, Fks], -1)
            Ds = np.where(D >= 0, D, 0)
            wD = wF * np.where((D >= 0)[:, None], c[ko, Fks], 0.0)
            paths.append((D, Ds, wD))
        (D1, D1s, w1), (D2, D2s, w2) = paths
        same = D1 == D2
        bad2 = (D2 < 0) | (D2 == nb[k1]) | same                           # valence 3 or the same diagonal
        bad1 = (D1 < 0) | (D1 == nb[k2])
        w1 = np.where(bad1[:, None], 0.0, np.where(same[:, None], np.maximum(w1, w2), w1))
        w2 = np.where(bad2[:, None], 0.0, w2)
        acc += w1 * np.nan_to_num(e[D1s]) + w2 * np.nan_to_num(e[D2s])
        wsum += w1 + w2
        out[j] = acc / wsum
    # a non-finite value spoils its own neighbourhood only, as in the average
    bad = ~np.isfinite(e)
    if bad.any():
        out[(nodal_average(t, bad.astype(float), p.shape[1]) > 0)[t]] = np.nan
    return out


def element_strain_operator(mesh):
    """(3 n_elements, 2 n_nodes) operator: [e_xx; e_yy; e_xy] at the element centres (1-point rule), per mm.

    Built once per mesh object and kept on it with a stamp of its node and element arrays (as
    :func:`femreg.mesh.tensor_structure`): a registration with refinement asks for the operator of the same mesh
    up to ten times (the solve's strain rule, the marking, the check).  Read-only (shared by every caller)."""
    stamp = _mesh.mesh_stamp(mesh)
    hit = getattr(mesh, _STRAIN_OP_ATTR, None)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    G, _ = centre_gradient_operators(mesh)
    op = sp.vstack([G["xx"], G["yy"], 0.5 * (G["xy"] + G["yx"])]).tocsr()
    for a in (op.data, op.indices, op.indptr):
        a.flags.writeable = False
    try:
        setattr(mesh, _STRAIN_OP_ATTR, (stamp, op))
    except (AttributeError, TypeError):   # pragma: no cover - a mesh type that takes no attributes: not kept
        pass
    return op


#: Attribute of a mesh holding its :func:`element_strain_operator` (with the stamp it was built for).
_STRAIN_OP_ATTR = "_femreg_strain_operator"


@functools.lru_cache(maxsize=1)
def _unit_centre_gradients() -> np.ndarray:
    """d N_k / dx and d N_k / dy (4 corners (0,0) (1,0) (1,1) (0,1) in (x, y) steps, 2) at the centre of the unit
    square, from scikit-fem (read-only)."""
    from skfem import Basis, ElementQuad1, MeshQuad1

    m = MeshQuad1(np.array([[0.0, 1.0, 1.0, 0.0], [0.0, 0.0, 1.0, 1.0]]), np.array([[0], [1], [2], [3]]))
    b = Basis(m, ElementQuad1(), quadrature=ELEMENT_CENTRE_RULE)
    V = np.array([[b.basis[k][0].grad[c][0, 0] for c in range(2)] for k in range(4)])
    V.flags.writeable = False
    return V


def centre_gradient_operators(mesh) -> tuple[dict[str, sp.csr_matrix], np.ndarray]:
    r"""Displacement-gradient operators at element centres, the building block of element-wise TV terms.

    Returns
    -------
    G : dict of (n_elements, 2 n_nodes) csr_matrix
        ``G["ab"] @ u`` = :math:`\partial u_a / \partial x_b` (a, b in x, y; 1) at each element centre, e.g.
        ``G["yy"]`` the lateral normal strain, ``0.5 * (G["xy"] + G["yx"])`` the shear strain.
    areas : (n_elements,) float
        Element areas (mm^2) for the centre rule, the natural weights of :math:`\int_\Omega`.
    """
    from skfem import Basis, ElementQuad1, ElementVector, MeshQuad1

    if not isinstance(mesh, MeshQuad1):
        raise ValueError(f"centre_gradient_operators needs a scikit-fem MeshQuad1, got {type(mesh).__name__}")
    ts = _mesh.tensor_structure(mesh)      # looked up at call time (tests switch the shortcut off)
    if ts is not None:
        # axis-aligned tensor mesh: the centre gradients of the unit square from scikit-fem, scaled by 1/hx and
        # 1/hy -- the same operators without a Basis over the whole mesh
        xs, ys, cell = ts
        I, J = np.meshgrid(np.arange(cell.shape[0]), np.arange(cell.shape[1]), indexing="ij")
        e, i, j = cell.ravel(), I.ravel(), J.ravel()
        node = _mesh.tensor_node_grid(mesh, xs, ys)
        corners = node[i[:, None] + np.array([0, 1, 1, 0]), j[:, None] + np.array([0, 0, 1, 1])]   # (n_el, 4)
        hx, hy = xs[i + 1] - xs[i], ys[j + 1] - ys[j]
        V = _unit_centre_gradients()                                               # (4 corners, 2)
        n_el, n = mesh.t.shape[1], 2 * mesh.p.shape[1]
        rows = np.broadcast_to(e[:, None], corners.shape).ravel()
        G = {}
        for a, an in enumerate("xy"):
            for b, (bn, h) in enumerate(zip("xy", (hx, hy))):
                G[an + bn] = sp.csr_matrix(((V[None, :, b] / h[:, None]).ravel(), (rows, (2 * corners + a).ravel())),
                                           shape=(n_el, n))
        areas = np.empty(n_el)
        areas[e] = hx * hy
        return G, areas
    basis = Basis(mesh, ElementVector(ElementQuad1()), quadrature=ELEMENT_CENTRE_RULE)
    n_el = mesh.t.shape[1]
    dofs = basis.element_dofs
    rows = np.broadcast_to(np.arange(n_el), dofs.shape).ravel()
    grads = np.stack([basis.basis[i][0].grad[:, :, :, 0] for i in range(basis.Nbfun)])   # (Nb, 2, 2, n_el)
    G = {}
    for a, an in enumerate("xy"):
        for b, bn in enumerate("xy"):
            G[an + bn] = sp.csr_matrix((grads[:, a, b].ravel(), (rows, dofs.ravel())), shape=(n_el, basis.N))
    areas = basis.dx[:, 0].copy()
    return G, areas


def inner_elements(mesh) -> np.ndarray:
    """(n_el,) bool: the elements of ``mesh`` with no node on its boundary."""
    bnd = np.zeros(mesh.p.shape[1], bool)
    bnd[mesh.boundary_nodes()] = True
    return ~bnd[mesh.t].any(axis=0)


def _ratio_elements(el_strain, mesh):
    """``(selected, inner, ex, ey)``: the elements :func:`lateral_ratio` and :func:`quadrant_ratios` read, the inner
    ones (all, on a mesh with fewer than 4) whose axial strain is at least half the median one over them; the inner
    ones; and the element strains' axial and lateral columns."""
    el_strain = np.asarray(el_strain, float)
    inner = inner_elements(mesh)
    if inner.sum() < 4:
        inner = np.ones(mesh.t.shape[1], bool)
    ex, ey = el_strain[:, 0], el_strain[:, 1]
    return inner & (np.abs(ex) >= 0.5 * np.median(np.abs(ex[inner]))), inner, ex, ey


def lateral_ratio(el_strain, mesh) -> float:
    r"""Lateral-to-axial strain ratio :math:`r = -\varepsilon_{yy}/\varepsilon_{xx}` of a displacement field
    (``el_strain`` (n_el, 3) element strains [exx, eyy, exy] on ``mesh``): the median of the element ratios over the
    inner elements (:func:`inner_elements`) whose axial strain is at least half the median one, so that a near-zero
    :math:`\varepsilon_{xx}` does not dominate.  About 1/2 for incompressible plane stress, :math:`\nu/(1-\nu)`
    (0.98 at :math:`\nu` = 0.495) for plane strain (:func:`femreg.material.model_ratio`).  NaN when fewer than 4
    such elements."""
    big, _, ex, ey = _ratio_elements(el_strain, mesh)
    if big.sum() < 4 or not np.any(np.abs(ex[big]) > 0):
        return float("nan")
    return float(np.median(-ey[big] / ex[big]))


def quadrant_ratios(el_strain, mesh) -> np.ndarray:
    r"""(4,) lateral-to-axial strain ratios :math:`-\varepsilon_{yy}/\varepsilon_{xx}` of the four quadrants of
    the inner elements (:func:`inner_elements`), split at their median depth and lateral position (shallow-left,
    shallow-right, deep-left, deep-right): each the median of the element ratios whose axial strain is at least half
    the median one over all inner elements (as :func:`lateral_ratio`); NaN for a quadrant with fewer than 4 such
    elements.  ``el_strain`` (n_el, 3) element strains on ``mesh``."""
    big, inner, ex, ey = _ratio_elements(el_strain, mesh)
    c = mesh.p[:, mesh.t].mean(axis=1)
    xm, ym = np.median(c[0, inner]), np.median(c[1, inner])
    big = big & (np.abs(ex) > 0)
    out = []
    for deep in (c[0] < xm, c[0] >= xm):
        for side in (c[1] < ym, c[1] >= ym):
            m = big & deep & side
            out.append(float(np.median(-ey[m] / ex[m])) if m.sum() >= 4 else float("nan"))
    return np.array(out)
