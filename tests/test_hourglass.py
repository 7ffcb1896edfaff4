"""Optional hourglass control of the momentum regularisers: affine fields stay free, the checkerboard
(hourglass) mode of bilinear quads that the edge-midpoint jumps (eq:Ae7) cannot see gets a penalty."""
import numpy as np
import pytest
from skfem import MeshQuad1

from femreg.regularizers import make_regularizer


def _mesh():
    return MeshQuad1.init_tensor(np.linspace(0, 6, 7), np.linspace(0, 4, 5))


@pytest.mark.parametrize("name", ["momentum-stress", "momentum-strain"])
def test_checkerboard_is_free_without_and_penalised_with_hourglass_control(name):
    m = _mesh()
    x, y = m.p
    ij = np.rint(x).astype(int) + np.rint(y).astype(int)
    checker = np.zeros(2 * m.p.shape[1])
    checker[1::2] = 1e-3 * (-1.0) ** ij                   # lateral node-to-node checkerboard
    affine = np.zeros_like(checker)
    affine[0::2], affine[1::2] = -0.01 * x + 0.002 * y, 0.005 * y + 0.001
    plain = make_regularizer(name, alpha=1.0)
    stab = make_regularizer(name, alpha=1.0, hourglass=1.0)
    for r in (plain, stab):
        r.setup(m)
    floor = plain.energy(np.zeros_like(checker))          # alpha * sum l_j sqrt(delta)
    assert plain.energy(checker) == pytest.approx(floor, rel=1e-9), "the jumps must not see the checkerboard"
    assert stab.energy(affine) == pytest.approx(plain.energy(affine), rel=1e-12), "affine fields stay free"
    n_el = m.t.shape[1]
    extra = stab.energy(checker) - plain.energy(checker)
    # each element: (u0 - u1 + u2 - u3) = +-4e-3 -> alpha * hourglass / 8 * 16e-6 per element
    assert extra == pytest.approx(n_el * 16e-6 / 8.0, rel=1e-9), extra


def test_hourglass_gradient_and_hessian():
    m = _mesh()
    reg = make_regularizer("momentum-stress", alpha=0.7, hourglass=2.0)
    reg.setup(m)
    rng = np.random.default_rng(0)
    u = 1e-2 * rng.standard_normal(2 * m.p.shape[1])
    g = reg.gradient(u)
    v = rng.standard_normal(u.size)
    h = 1e-6
    fd = (reg.energy(u + h * v) - reg.energy(u - h * v)) / (2 * h)
    assert abs(fd - g @ v) < 1e-6 * max(1.0, abs(fd)), (fd, g @ v)
    H = reg.hessian(u)
    assert abs(H - H.T).max() < 1e-12
    assert np.linalg.eigvalsh(H.toarray()).min() > -1e-10


def test_bad_hourglass_weight():
    with pytest.raises(ValueError, match="hourglass"):
        make_regularizer("momentum-stress", hourglass=-1.0)
