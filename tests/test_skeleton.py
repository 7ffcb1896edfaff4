import numpy as np
import pytest
from skfem import MeshQuad1

from femreg.cli import main
from femreg.regularizers import available_regularizers, make_regularizer


def test_cli_help_and_no_command(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    assert main([]) == 2


def test_unknown_regularizer_names_it():
    with pytest.raises(ValueError, match="nope"):
        make_regularizer("nope")
    assert {"strain", "strain-incompressible"} <= set(available_regularizers())


@pytest.mark.parametrize("name", ["strain", "strain-incompressible"])
def test_strain_energy_of_affine_field(name):
    # u = (a x, b y) on a 3 x 2 mm rectangle: sym grad u = diag(a, b), div u = a + b.
    mesh = MeshQuad1.init_tensor(np.linspace(0, 3, 7), np.linspace(0, 2, 5))
    reg = make_regularizer(name, alpha=2.0)
    reg.setup(mesh)
    a, b = 0.01, -0.004
    u = np.zeros(2 * mesh.p.shape[1])
    u[0::2] = a * mesh.p[0]
    u[1::2] = b * mesh.p[1]
    area = 6.0
    expected = 0.5 * 2.0 * (a**2 + b**2) * area
    if name == "strain-incompressible":
        expected += 0.5 * 2.0 * 100.0 * (a + b) ** 2 * area
    assert reg.energy(u) == pytest.approx(expected, rel=1e-12)
    H = reg.hessian(u)
    assert abs(H - H.T).max() < 1e-12


def test_default_alphas_come_from_the_study_file():
    import json
    from pathlib import Path

    import femreg

    data = json.loads((Path(femreg.__file__).parent / "data" / "default_alphas.json").read_text())
    assert set(data["alphas"]) == {"strain", "strain-incompressible", "momentum-strain", "momentum-stress"}
    for name, value in data["alphas"].items():
        assert make_regularizer(name).alpha == pytest.approx(value, rel=1e-12), name
