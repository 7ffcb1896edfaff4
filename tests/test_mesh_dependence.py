"""femreg.quality.mesh_dependence: the strain change between two meshes offset by a fraction of an element.  An
affine field is the same on every mesh; a smooth field's recovered strain nearly so, its element strain (blocks
whose edges follow element lines) clearly not; on real frames the default strain image moves little with the mesh.
The in vivo part is skipped when ../shared/data/invivo_rf is absent."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest
from skfem import MeshQuad1

import femreg
from femreg.errors import InputError
from femreg.quality import mesh_dependence

REPO = Path(__file__).resolve().parents[1]


def _result(field, offset):
    """A result holding ``field`` interpolated at the nodes of a 1 mm tensor mesh over 20 x 16 mm moved by
    ``offset`` (mm)."""
    m = MeshQuad1.init_tensor(np.arange(0.0, 21.0) + offset[0], np.arange(0.0, 17.0) + offset[1])
    u = np.empty(2 * m.p.shape[1])
    u[0::2], u[1::2] = field(m.p[0], m.p[1])
    return femreg.RegistrationResult(m, u, shape=(200, 160), spacing=(0.1, 0.1), origin=(0.0, 0.0))


def _smooth(x, y):
    return 0.02 * np.sin(x / 3.0) * np.cos(y / 4.0), 0.015 * np.cos(x / 5.0 + y / 3.0)


def test_affine_field_does_not_depend_on_the_mesh():
    def affine(x, y):
        return -0.01 * x + 0.003 * y, 0.004 * x + 0.005 * y
    d = mesh_dependence(_result(affine, (0, 0)), _result(affine, (0.5, 0.4)))
    assert max(d["exx"], d["eyy"], d["exy"]) < 1e-10, d
    assert d["n"] > 10000, d


def test_element_strain_is_mesh_bound_recovered_much_less():
    a, b = _result(_smooth, (0, 0)), _result(_smooth, (0.5, 0.4))
    rec, el = mesh_dependence(a, b), mesh_dependence(a, b, strain="element")
    # measured: recovered exx / eyy / exy 0.017 / 0.027 / 0.030, element 0.162 / 0.157 / 0.101 (3.4-9.7x)
    for k in ("exx", "eyy", "exy"):
        assert rec[k] < 0.045, rec
        assert el[k] > 0.07 and el[k] > 2.5 * rec[k], (rec, el)


def test_bad_input():
    a = _result(_smooth, (0, 0))
    with pytest.raises(InputError):
        mesh_dependence(a, a, step=0.0)
    with pytest.raises(InputError):
        mesh_dependence(a, _result(_smooth, (40.0, 0.0)))


def _demo07():
    spec = importlib.util.spec_from_file_location("demo07_invivo_md", REPO / "demos" / "07_invivo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


DEMO = _demo07()
DATA = DEMO.data_dir()


@pytest.mark.skipif(DATA is None, reason="in vivo data folder ../shared/data/invivo_rf not present")
def test_invivo_strain_image_is_not_bound_to_the_mesh():
    """seq304 frames 1 -> 3, a 12 x 12.8 mm piece, registered with the defaults twice: the second time cropped by
    25 samples and 3 lines more (0.5 mm x 0.6 mm, most of an element), so the mesh sits elsewhere on the tissue."""
    fr = femreg.io.read_frames(DATA / "seq304", shape=DEMO.SHAPE, spacing=DEMO.SPACING)
    rows, cols = DEMO.QUICK_CROP["seq304"]
    sp = DEMO.SPACING
    res = []
    for da, dl in ((0, 0), (25, 3)):
        r0, c0 = rows.start + da, cols.start + dl
        ref, mov = (fr.frames[k][r0:rows.stop, c0:cols.stop] for k in (0, 2))
        res.append(femreg.register(ref, mov, spacing=sp, origin=(r0 * sp[0], c0 * sp[1])))
    rec, el = mesh_dependence(*res), mesh_dependence(*res, strain="element")
    # measured: recovered exx / eyy / exy 0.103 / 0.126 / 0.187; element 0.156 / 0.147 / 0.263
    assert rec["exy"] < 0.25 and rec["eyy"] < 0.17 and rec["exx"] < 0.14, rec
    assert all(el[k] > rec[k] for k in ("exx", "eyy", "exy")), (rec, el)
