"""Cases from ``benchmarks/refine_stress.py`` where the default refinement went wrong, reduced to the rule at fault.

A soft r 5 mm inclusion in a 60 x 40 mm image: the shear-traction jumps around its rim form runs (two half rims,
24 x 13 mm) longer than the 20 mm by which :data:`femreg.refine.DEEP_REFINEMENT` tells a layer across the image,
so its rim was relaxed as a layer (total strain error 7.48 % unrefined, 12.68 % refined; 4.72 % with the rim left
alone).  Here: a disk turning inside a still surrounding, whose rim's shear-traction jumps run around it.
"""
import dataclasses

import numpy as np
import pytest

from femreg.mesh import roi_mesh, tensor_structure
from femreg.refine import DEEP_REFINEMENT, RING_ASPECT, relaxed_edges
from _nodal_field import nodal as _nodal

SPACING, ORIGIN = (0.04, 0.3), (2.0, -20.0)
SHAPE = (1000, 134)                  # 40 x 40 mm
#: every edge that qualifies (the default cap, 5 % of the interior edges, would keep a part of a long run)
OPTS = dataclasses.replace(DEEP_REFINEMENT, relax_cells=False, relax_max_fraction=1.0)


def _mesh():
    return roi_mesh(SHAPE, SPACING, ORIGIN, element_size=(1.5, 1.5))


def _turning_disk(centre, radius, width=2.0, angle=0.01):
    """1 % compression plus a disk of ``radius`` turned by ``angle`` (rad), the turn fading to 0 over ``width`` mm
    outside it: a ring of shear strain whose two faces carry the shear-traction jumps."""
    def f(p):
        d = p - np.asarray(centre)
        r = np.hypot(d[:, 0], d[:, 1])
        w = np.clip((radius + width - r) / width, 0.0, 1.0)
        return np.column_stack([-0.01 * p[:, 0] - angle * w * d[:, 1], angle * w * d[:, 0]])
    return f


def _band(x0, x1, slide=0.3):
    def f(p):
        return np.column_stack([-0.01 * p[:, 0], slide * np.clip((p[:, 0] - x0) / (x1 - x0), 0.0, 1.0)])
    return f


def _extent(segs):
    return max(np.ptp(np.r_[segs[:, 0], segs[:, 1]]), np.ptp(np.r_[segs[:, 2], segs[:, 3]]))


def test_a_rim_inside_a_large_image_is_not_relaxed_as_a_layer():
    m = _mesh()
    u = _nodal(m, _turning_disk((22.0, 0.0), 10.0))
    # the rim stands out as runs longer than the layer length: relaxed as a layer without the ring test
    plain = relaxed_edges(m, u, dataclasses.replace(OPTS, relax_ring=None))
    assert len(plain) > 20 and _extent(plain) >= OPTS.relax_min_length
    assert OPTS.relax_ring == RING_ASPECT
    assert len(relaxed_edges(m, u, OPTS)) == 0


def test_a_band_across_the_image_is_still_relaxed():
    m = _mesh()
    xs, _, _ = tensor_structure(m)
    u = _nodal(m, _band(xs[10], xs[11]))
    segs = relaxed_edges(m, u, OPTS)
    assert len(segs) == len(relaxed_edges(m, u, dataclasses.replace(OPTS, relax_ring=None))) > 0
    assert set(segs[:, 0]) == {xs[10], xs[11]}


def test_the_ring_option_is_checked():
    from femreg.errors import InputError

    with pytest.raises(InputError):
        dataclasses.replace(DEEP_REFINEMENT, relax_ring=0.0)
    with pytest.raises(InputError):
        dataclasses.replace(DEEP_REFINEMENT, relax_ring=1.5)
