"""The shear-strain product: e_xy per element with a predicted precision from the lateral and axial displacement
information the element holds.

``e_xy = (du_x/dy + du_y/dx) / 2``.  Across a slip band parallel to the probe face (layers sliding laterally) the
signal is ``du_y/dx``: the *lateral* displacement differentiated along depth, and lateral displacement is what RF
data measure worst (the lateral speckle cell, about the beam width, is 3-10x the axial one, and there is no
carrier laterally).  The precision of a time-delay / displacement estimate from a window follows the Cramer-Rao
scaling ``sigma_u ~ c sqrt(1 / rho^2 - 1) / sqrt(N)`` with ``c`` the speckle cell along the motion, ``rho`` the
correlation after registration and ``N`` the number of independent speckle cells in the window (W. F. Walker,
G. E. Trahey, IEEE Trans. UFFC 42(2):301-308, 1995).  Per element (sizes ``h_x, h_y``), with that scaling's
constant set to 1:

    sigma_ux = c_x s,  sigma_uy = c_y s,  s = sqrt((1 / rho^2 - 1) / N),  N = h_x h_y / (c_x c_y),
    sigma_exy = sqrt(sigma_ux^2 / h_y^2 + sigma_uy^2 / h_x^2) / sqrt(2)

(the two nodal differences of each derivative independent).  This is the data's precision, not the registration's:
the regulariser trades it for bias (a thin band is widened and its peak lowered), so ``sigma`` is an upper bound
on the noise and says nothing about that bias, which needs elements (and a weight) that let the band through.
Measured on simulated band pairs (1 % compression, a 1-2 mm band sliding 0.15-0.3 mm, 5.5 and 7.5 MHz, SNR 30 dB,
R_P_sigma): away from the band the actual RMS error of e_xy was 0.02-0.06 % against a median ``sigma`` of
1.8-3.2 %, i.e. the constant-1 bound is 30-80x loose (the RF carrier and the regulariser both do better than an
envelope window): read ``sigma`` and ``snr`` as relative measures that rank elements (low lateral information,
low NCC), not as calibrated error bars.
"""
from __future__ import annotations

import numpy as np

from .errors import InputError
from .fields import element_strains

__all__ = ["shear_strain_map", "narrow_elements", "slip_settings", "SLIP_AXIAL_MM", "SLIP_TRACTION"]

#: Axial element size (mm) and tangential-traction weight of :func:`slip_settings`: on 1 % compression with 1-2 mm
#: bands sliding 0.1-0.3 mm (benchmarks/shear_bands.py, 7.5 and 5.5 MHz) they brought the band's peak e_xy from
#: 11-59 % to 64-101 % of the truth and the total strain error from 55-75 % to 25-42 %; on smooth fields they cost
#: accuracy (robustness benchmark: uniform compression 0.1-0.6 % -> 0.8-11 %, bending 5.8 -> 9.3 %).
SLIP_AXIAL_MM = 0.35
SLIP_TRACTION = 0.03


def _element_sizes(mesh):
    p = np.asarray(mesh.p, float)[:, np.asarray(mesh.t)]            # (2, 4, n_el)
    return np.ptp(p[0], axis=0), np.ptp(p[1], axis=0)


def shear_strain_map(result, reference_image=None, *, cell=None) -> dict:
    """e_xy per element of a registration and its predicted precision (module docstring).

    Parameters
    ----------
    result : RegistrationResult
        With its per-element NCC ``quality`` (:func:`femreg.register` sets it).
    reference_image : (n_axial, n_lateral) array, optional
        The registered reference image, for the speckle cell (:func:`femreg.speckle.speckle_cell`, the
        envelope autocorrelation FWHM with tissue structure divided out); or give ``cell``.
    cell : (2,) mm, optional
        (axial, lateral) speckle cell.

    Returns
    -------
    dict of (n_elements,) arrays: ``exy`` (fraction, element centre), ``sigma`` (predicted standard deviation of
    ``exy``, fraction; inf where the element's NCC is <= 0 or missing), ``snr`` = ``|exy| / sigma``,
    ``lateral_cells`` (lateral element size / lateral speckle cell: below 1 the element sees less than one
    lateral speckle and its ``du_y`` is poorly measured), plus ``cell`` (2,) mm.
    """
    if getattr(result, "mesh", None) is None or getattr(result, "u", None) is None:
        raise InputError("shear_strain_map needs a RegistrationResult (mesh and u)")
    if cell is None:
        if reference_image is None:
            raise InputError("shear_strain_map needs the reference image or the speckle cell "
                             "(cell=(axial, lateral) mm)")
        from .speckle import speckle_cell

        cell = speckle_cell(np.asarray(reference_image, float), result.spacing)
    c = np.asarray(cell, float).ravel()
    if c.shape != (2,) or not np.all(np.isfinite(c)) or not np.all(c > 0):
        raise InputError(f"cell must be two positive lengths (axial, lateral) mm, got {cell!r}")
    mesh = result.mesh
    exy = element_strains(mesh.p, mesh.t, result.u)[:, 2]
    hx, hy = _element_sizes(mesh)
    q = getattr(result, "quality", None)
    rho = np.full(exy.shape, np.nan) if q is None else np.asarray(q, float)
    rho = np.where(np.isfinite(rho), np.clip(rho, 0.0, 0.9999), 0.0)
    n = np.maximum(hx * hy / (c[0] * c[1]), 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(rho > 0, np.sqrt((1.0 / rho**2 - 1.0) / n), np.inf)
        sigma = np.sqrt((c[0] * s / hy) ** 2 + (c[1] * s / hx) ** 2) / np.sqrt(2.0)
        snr = np.where(np.isfinite(sigma) & (sigma > 0), np.abs(exy) / sigma, 0.0)
    return {"exy": exy, "sigma": sigma, "snr": snr, "lateral_cells": hy / c[1], "cell": c}


def narrow_elements(shear_map) -> np.ndarray:
    """(n_elements,) bool: the elements of :func:`shear_strain_map`'s ``shear_map`` narrower than one lateral speckle
    cell.  An element exactly one cell wide (4 lines of 0.2 mm under a 0.8 mm cell) is not: the ratio of the two
    lengths, each a sum of pixel steps, is compared with a relative tolerance of 1e-6 against rounding."""
    cells = np.asarray(shear_map["lateral_cells"], float).ravel()
    return np.isfinite(cells) & (cells < 1.0 - 1e-6)


def slip_settings(result, *, axial_mm: float = SLIP_AXIAL_MM, shear_traction: float = SLIP_TRACTION) -> dict:
    """Keyword arguments of :func:`femreg.register` that let a thin slip band parallel to the probe face through,
    from a default R_P_sigma / R_P_eps ``result`` of the same pair: elements ``axial_mm`` thick (the result's
    lateral size), alpha scaled by the element-area ratio so that the weight per area (``alpha_eff``,
    :mod:`femreg.scaling`) stays the default's, and ``regularizer_options={"shear_traction": shear_traction}``
    (the momentum regulariser's tangential traction jump weighted down).  Not the default: it costs accuracy on
    smooth fields and inclusions (README, "Shear strain e_xy and sliding layers")."""
    mesh = getattr(result, "mesh", None)
    if mesh is None or not np.isfinite(getattr(result, "alpha", np.nan)):
        raise InputError("slip_settings needs a RegistrationResult (mesh and alpha)")
    a = float(axial_mm)
    if not (np.isfinite(a) and a > 0):
        raise InputError(f"axial_mm must be a positive length (mm), got {axial_mm!r}")
    hx, hy = (float(np.median(h)) for h in _element_sizes(mesh))
    base = getattr(getattr(result, "refinement", None), "base_size", None)
    if base is not None:
        hx, hy = base                  # refined: the mesh it started from sets the size and the weight
    return {"element_size": (a, hy), "alpha": float(result.alpha) * a / hx,
            "regularizer_options": {"shear_traction": float(shear_traction)}}
