"""femreg.speckle.speckle_cell: the speckle cell with tissue structure divided out (the shear product's lateral
cell), against the whole-envelope cell of speckle_statistics, on simulated speckle with and without a layered
echogenicity, with a zero fill below the echo, and on a real recording; femreg.shear.narrow_elements."""
from pathlib import Path

import numpy as np
import pytest

from femreg.shear import narrow_elements
from femreg.speckle import speckle_cell, speckle_statistics

INVIVO = Path(__file__).resolve().parents[2] / "shared" / "data" / "invivo_rf" / "seq304" / "frame1.raw"


def _speckle(probe):
    from forward import fields as F
    from forward.pairs import make_pair

    d = make_pair(F.compression(0.01), probe, (30.0, 30.0), 30.0, 0)
    return np.asarray(d.ref, float), d.spacing


def _layered(img, spacing, seed=3, db=6.0, size_mm=(2.0, 10.0)):
    """``img`` times a smooth random echogenicity of ``db`` dB RMS in patches ``size_mm`` (axial, lateral)."""
    from scipy.ndimage import gaussian_filter

    g = gaussian_filter(np.random.default_rng(seed).standard_normal(img.shape),
                        (size_mm[0] / spacing[0], size_mm[1] / spacing[1]))
    return img * 10.0 ** (db * g / g.std() / 20.0)


@pytest.mark.parametrize("probe", ["L7", "L3"])
def test_uniform_speckle_keeps_its_cell(probe):
    # measured: identical to the whole envelope's cell (0.27 x 1.20 mm under L7, 0.62 x 3.00 under L3)
    img, sp = _speckle(probe)
    ref = speckle_statistics(img, sp).cell
    assert np.allclose(speckle_cell(img, sp), ref, rtol=0.10)


@pytest.mark.parametrize("probe", ["L7", "paper"])
def test_layered_echogenicity_is_divided_out(probe):
    img, sp = _speckle(probe)
    uniform = speckle_statistics(img, sp).cell
    layered = _layered(img, sp)
    whole = speckle_statistics(layered, sp).cell
    # the structure widens the whole envelope's cell (measured 4.5-5.7x axially, 2.7-4.3x laterally) ...
    assert whole[0] > 2.0 * uniform[0] and whole[1] > 1.5 * uniform[1]
    # ... and not this one (measured: the uniform speckle's cell exactly)
    assert np.allclose(speckle_cell(layered, sp), uniform, rtol=0.15)


def test_zero_fill_below_the_echo_is_left_out():
    img, sp = _speckle("L7")
    padded = np.vstack([img, np.zeros((img.shape[0] // 4, img.shape[1]))])
    assert np.allclose(speckle_cell(padded, sp), speckle_cell(img, sp), rtol=0.10)
    assert np.all(np.isnan(speckle_cell(np.zeros((64, 32)), sp)))


@pytest.mark.skipif(not INVIVO.exists(), reason="in vivo RF frames not present")
def test_in_vivo_cell_without_tissue_structure():
    img = np.fromfile(INVIVO, "<f4").reshape(2000, 128).astype(float)    # full depth, zero rows at the bottom
    whole = speckle_statistics(img, (0.02, 0.2)).cell
    cell = speckle_cell(img, (0.02, 0.2))
    # measured 0.48 x 0.80 mm against 0.92 x 3.20 (whole envelope, tissue layers included)
    assert cell[1] <= 0.5 * whole[1] and cell[0] < whole[0]
    assert 0.2 <= cell[0] <= 1.0 and 0.4 <= cell[1] <= 1.6


def test_narrow_elements_tolerates_rounding():
    # an element exactly one cell wide, computed as 4 x 0.2 mm / 0.8 mm, is not narrow
    w = 0.2 + 0.2 + 0.2 + 0.2
    cells = np.array([w / 0.8 - 1e-12, 0.6 / 0.8, 1.25, np.nan])
    assert narrow_elements({"lateral_cells": cells}).tolist() == [False, True, False, False]
