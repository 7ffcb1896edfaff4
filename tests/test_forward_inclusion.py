r"""Circular elastic inclusion under remote uniaxial stress: FE interior strain vs the classical closed form.

Derivation (2D, plane strain or plane stress; Eshelby 1957, Proc. R. Soc. A 241:376, doi:10.1098/rspa.1957.0133;
Muskhelishvili, *Some Basic Problems of the Mathematical Theory of Elasticity*, 1953, §56; Hardiman 1954,
Q. J. Mech. Appl. Math. 7:226, doi:10.1093/qjmam/7.2.226).  With Kolosov's constant
:math:`\kappa = 3-4\nu` (plane strain) or :math:`(3-\nu)/(1+\nu)` (plane stress), the in-plane 2D bulk modulus is
:math:`k = 2\mu/(\kappa-1)` (= :math:`\lambda+\mu`, resp. :math:`\lambda^*+\mu`), and the 2D Eshelby tensor of a
circle splits into an equibiaxial part :math:`S_h = k/(k+\mu) = 2/(\kappa+1)` and a deviatoric part
:math:`S_d = (k+2\mu)/(2(k+\mu)) = \kappa/(\kappa+1)`.  The equivalent-inclusion method gives a uniform interior
stress; splitting the remote uniaxial stress :math:`\sigma_\infty` (along x) into :math:`p = s = \sigma_\infty/2`
(equibiaxial + pure shear parts),

.. math::
    \frac{p_{in}}{p} = \frac{\mu_1(\kappa+1)}{2\mu_1 + \mu(\kappa_1-1)}, \qquad
    \frac{s_{in}}{s} = \frac{\mu_1(\kappa+1)}{\mu + \kappa\mu_1},

(the first is also Lamé's thick-cylinder solution), and with the inclusion's 2D law
:math:`\varepsilon_{xx} = p_{in}/(2k_1) + s_{in}/(2\mu_1)`, :math:`\varepsilon_{yy} = p_{in}/(2k_1) - s_{in}/(2\mu_1)`.
The remote stress follows from the far-field strain :math:`\varepsilon_\infty = -c/B` of the homogeneous block:
:math:`\sigma_\infty = E'\varepsilon_\infty`, :math:`E' = 4k\mu/(k+\mu)` (E in plane stress, E/(1-nu^2) in plane
strain).  The FE model: a 400 mm block, inclusion of diameter 15 mm at its centre, whole top face compressed with
slip, bottom sliding (so the far field is uniaxial stress); the inclusion is 27 radii from every face.
"""
import numpy as np
import pytest

import forward
from forward.elasticity import lame_parameters


def closed_form(model, E1, E, nu, eps_inf):
    def kappa_mu_k(Ei):
        mu = Ei / (2 * (1 + nu))
        kappa = 3 - 4 * nu if model == "plane-strain" else (3 - nu) / (1 + nu)
        return kappa, mu, 2 * mu / (kappa - 1)

    ka, mu, k = kappa_mu_k(E)
    ka1, mu1, k1 = kappa_mu_k(E1)
    # consistency with the Lamé parameters used by the solver
    lam, mu_s = lame_parameters(E, nu, model)
    assert np.isclose(k, lam + mu_s) and np.isclose(mu, mu_s)
    sig = 4 * k * mu / (k + mu) * eps_inf
    p = s = sig / 2
    p_in = p * mu1 * (ka + 1) / (2 * mu1 + mu * (ka1 - 1))
    s_in = s * mu1 * (ka + 1) / (mu + ka * mu1)
    return np.array([p_in / (2 * k1) + s_in / (2 * mu1), p_in / (2 * k1) - s_in / (2 * mu1)])


@pytest.mark.parametrize("model", ["plane-strain", "plane-stress"])
@pytest.mark.parametrize("E1", [40.0, 5.0])
def test_circular_inclusion_matches_eshelby(model, E1):
    B, c, nu, E = 400.0, 1.0, 0.495, 10.0
    sol = forward.solve_elasticity(model, inclusion_modulus=E1, background_modulus=E, poisson=nu, block_mm=B,
                                   inclusion_diameter_mm=15.0, inclusion_depth_mm=B / 2, patch_mm=None,
                                   compression_mm=c, bottom="slip", mesh_size_mm=0.5, coarse_size_mm=12.0,
                                   refine_region_mm=())
    rng = np.random.default_rng(0)
    r, th = 5.0 * np.sqrt(rng.uniform(size=200)), rng.uniform(0, 2 * np.pi, 200)
    pts = np.c_[B / 2 + r * np.cos(th), r * np.sin(th)]
    e = sol.strain(pts)
    ref = closed_form(model, E1, E, nu, -c / B)
    mean = e[:, :2].mean(axis=0)
    rel = np.abs(mean - ref) / np.abs(ref)
    spread = (e[:, 0].max() - e[:, 0].min()) / abs(mean[0])
    print(f"{model} E1={E1}: FE interior [exx, eyy] = {mean}, closed form {ref}, rel. err {rel}, "
          f"exx spread {spread:.2e}, DOFs {sol.info['n_dofs']}")
    assert np.all(rel < 0.01), f"{model} E1={E1}: FE {mean} vs closed form {ref}: rel. error {rel}"
    assert spread < 0.02, f"{model} E1={E1}: interior exx not uniform, relative spread {spread:.3f}"
    assert np.max(np.abs(e[:, 2])) < 0.02 * abs(mean[0]), f"interior shear {np.max(np.abs(e[:, 2])):.2e} not ~0"
    # far field is the homogeneous uniaxial state (exx = -c/B), checks the boundary conditions
    far = sol.strain(np.array([[B / 2, 150.0], [100.0, -150.0]]))
    assert np.allclose(far[:, 0], -c / B, rtol=0.01), f"far-field exx {far[:, 0]} vs {-c / B}"
