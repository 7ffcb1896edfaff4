"""Manufactured-solution convergence of the P2 elasticity discretisation used by forward.elasticity.

u = (sin(pi x) sin(pi y), sin(2 pi x) sin(pi y)) on the unit square (zero on the boundary), constant Lamé
parameters at nu = 0.495 (lambda/mu ~ 99: the locking regime of P1).  Body force f = -div sigma(u) =
-mu lap u - (lambda + mu) grad div u.  Expected rates for P2: L2 3, H1 (semi-norm) 2.
"""
import numpy as np
import pytest
from skfem import Basis, ElementTriP2, ElementVector, Functional, LinearForm, MeshTri1, asm, condense, solve

from forward.elasticity import elasticity_form, lame_parameters

pi = np.pi


def exact(x, y):
    a = np.sin(pi * x) * np.sin(pi * y)
    b = np.sin(2 * pi * x) * np.sin(pi * y)
    return np.array([a, b])


def exact_grad(x, y):
    return np.array([[pi * np.cos(pi * x) * np.sin(pi * y), pi * np.sin(pi * x) * np.cos(pi * y)],
                     [2 * pi * np.cos(2 * pi * x) * np.sin(pi * y), pi * np.sin(2 * pi * x) * np.cos(pi * y)]])


def body_force(x, y, lam, mu):
    a = np.sin(pi * x) * np.sin(pi * y)
    b = np.sin(2 * pi * x) * np.sin(pi * y)
    lap = np.array([-2 * pi ** 2 * a, -5 * pi ** 2 * b])
    graddiv = np.array([-pi ** 2 * a + 2 * pi ** 2 * np.cos(2 * pi * x) * np.cos(pi * y),
                        pi ** 2 * np.cos(pi * x) * np.cos(pi * y) - pi ** 2 * b])
    return -mu * lap - (lam + mu) * graddiv


@pytest.mark.parametrize("model", ["plane-strain", "plane-stress"])
def test_p2_manufactured_rates(model):
    lam, mu = lame_parameters(10.0, 0.495, model)
    lam, mu = float(lam), float(mu)

    @LinearForm
    def load(v, w):
        f = body_force(w.x[0], w.x[1], lam, mu)
        return f[0] * v[0] + f[1] * v[1]

    @Functional
    def l2(w):
        e = w["uh"] - exact(w.x[0], w.x[1])
        return e[0] ** 2 + e[1] ** 2

    @Functional
    def h1(w):
        e = w["uh"].grad - exact_grad(w.x[0], w.x[1])
        return np.sum(e ** 2, axis=(0, 1))

    hs, e0, e1 = [], [], []
    for k in range(2, 6):
        m = MeshTri1().refined(k)
        ib = Basis(m, ElementVector(ElementTriP2()), intorder=5)
        K = asm(elasticity_form(), ib, lam=lam, mu=mu)
        f = asm(load, ib)
        u = solve(*condense(K, f, D=ib.get_dofs()))
        uh = ib.interpolate(u)
        hs.append(m.param())
        e0.append(np.sqrt(l2.assemble(ib, uh=uh)))
        e1.append(np.sqrt(h1.assemble(ib, uh=uh)))
    r0 = np.polyfit(np.log(hs), np.log(e0), 1)[0]
    r1 = np.polyfit(np.log(hs), np.log(e1), 1)[0]
    assert abs(r0 - 3.0) < 0.15, f"{model}: L2 rate {r0:.3f} (errors {e0})"
    assert abs(r1 - 2.0) < 0.1, f"{model}: H1 rate {r1:.3f} (errors {e1})"
    print(f"{model}: L2 rate {r0:.3f}, H1 rate {r1:.3f}, finest L2 {e0[-1]:.2e} H1 {e1[-1]:.2e}")
    assert e0[-1] < 1e-4 and e1[-1] < 2e-2, f"{model}: finest errors L2 {e0[-1]:.2e}, H1 {e1[-1]:.2e}"
