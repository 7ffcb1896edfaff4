"""``refine=`` takes the names the CLI's ``--refine`` takes ("auto", "slip", "none" / "off", any case), so what the
README shows for the command line works the same from Python; a bad value is a typed error naming the choices."""
import numpy as np
import pytest

import femreg
from femreg.errors import InputError
from femreg.refine import DEEP_REFINEMENT, SLIP_REFINEMENT, as_refinement
from femreg.volume_refine import VOLUME_REFINEMENT, as_volume_refinement


@pytest.mark.parametrize("name, expected", [("auto", DEEP_REFINEMENT), ("slip", SLIP_REFINEMENT),
                                            (" Slip ", SLIP_REFINEMENT), ("AUTO", DEEP_REFINEMENT),
                                            ("none", None), ("Off", None), (0, None), (None, None)])
def test_refine_names_resolve_as_on_the_command_line(name, expected):
    assert as_refinement(name) is expected


@pytest.mark.parametrize("bad", ["deep", -1, 1.5])
def test_a_bad_refine_value_names_the_choices(bad):
    with pytest.raises(InputError) as e:
        as_refinement(bad)
    assert ("'slip'" in str(e.value)) or ("0 or more" in str(e.value))


def test_volumes_take_none_and_auto_by_name_and_refuse_slip():
    assert as_volume_refinement("None") is None and as_volume_refinement("Auto") is VOLUME_REFINEMENT
    with pytest.raises(InputError, match="2D only"):
        as_volume_refinement("slip")


def test_register_with_refine_slip_is_the_slip_refinement():
    from forward import fields as F
    from forward.pairs import make_pair

    d = make_pair(F.ShearBand(8.0, 1.0, 0.15, 0.01), "L7", (16.0, 12.0), 30.0, 0)
    kw = dict(spacing=d.spacing, origin=d.origin)
    by_name = femreg.register(d.ref, d.mov, refine="slip", **kw)
    by_object = femreg.register(d.ref, d.mov, refine=SLIP_REFINEMENT, **kw)
    default = femreg.register(d.ref, d.mov, **kw)
    off = femreg.register(d.ref, d.mov, refine="none", **kw)
    assert by_name.success and by_name.refinement.passes and by_name.refinement.passes[0]["slip_cells"] > 0
    assert np.array_equal(by_name.u, by_object.u)
    # the slip refinement is not the default one: its mesh and its field differ
    assert by_name.mesh.t.shape[1] != default.mesh.t.shape[1] or not np.array_equal(by_name.u, default.u)
    # "none" is no refinement: the unrefined mesh
    assert getattr(off, "refinement", None) is None or not off.refinement.passes
    assert off.mesh.t.shape[1] <= min(by_name.mesh.t.shape[1], default.mesh.t.shape[1])
