"""Options of register and track that change how the work is done: ``linear_solver=``, ``coarse_to_fine=``
(``strategy="paper"``) and track's ``grid="reference"`` -- each checked by what it must change, and leave alone."""
import numpy as np
import pytest

import femreg
import femreg.solver
from femreg.image import SplineImage, pixel_axes
from femreg.registration import COARSE_TO_FINE_STRAIN
from femreg.synthetic import speckle_image, speckle_pair, warp_image

SP = (0.025, 0.2)


def compression(e, yc):
    return lambda p: np.column_stack([-e * p[:, 0], 0.5 * e * (p[:, 1] - yc)])


@pytest.fixture
def solvers(monkeypatch):
    """Every SPDSolver built during a call (the linear solver each Gauss-Newton solve used)."""
    made = []
    real = femreg.solver.SPDSolver

    class Spy(real):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

    monkeypatch.setattr(femreg.solver, "SPDSolver", Spy)
    return made


def test_linear_solver_reaches_every_solve_and_all_give_the_same_registration(solvers):
    ref, mov = speckle_pair(compression(0.02, 8.0), (600, 80), SP, seed=3, snr_db=30)
    base = None
    for name, factor in (("auto", "cholesky"), ("cholesky", "cholesky"), ("splu", "splu"), ("spsolve", None),
                         ("amg-cg", None)):
        solvers.clear()
        res = femreg.register(ref, mov, spacing=SP, linear_solver=name)
        assert res.success, (name, res.message)
        # the envelope level and the final solve both, with the method asked for (auto: banded Cholesky here)
        assert len(solvers) >= 2 and all(s.method == name for s in solvers), (name, [s.method for s in solvers])
        assert all(s.last_method == factor for s in solvers), (name, [s.last_method for s in solvers])
        assert (res.solver_result.n_factorizations == 0) == (name == "spsolve")   # spsolve keeps no factor
        if base is None:
            base = res
        # measured: 0 (auto = cholesky), 1.5e-15 (splu, spsolve), 3.8e-14 (amg-cg, CG to 1e-10) of max |u|
        assert res.nit == base.nit
        assert np.abs(res.u - base.u).max() <= 1e-10 * np.abs(base.u).max(), name
    with pytest.raises(ValueError, match="linear solver"):
        femreg.register(ref, mov, spacing=SP, linear_solver="bogus")


@pytest.mark.parametrize("strain", [0.02, 0.005])
def test_coarse_to_fine_improves_the_start_and_auto_follows_the_global_strain(strain):
    f = compression(strain, 8.0)
    ref, mov = speckle_pair(f, (800, 80), SP, seed=3, snr_db=30)          # 20 x 16 mm
    kw = dict(spacing=SP, strategy="paper", blockmatch_options=dict(window=(2.5, 4.5)))
    on = femreg.register(ref, mov, coarse_to_fine=True, **kw)
    off = femreg.register(ref, mov, coarse_to_fine=False, **kw)
    auto = femreg.register(ref, mov, coarse_to_fine="auto", **kw)
    assert on.success and off.success
    assert "coarse_pass" in on.timings and "coarse_pass" not in off.timings
    # the coarse pass starts the final solve much closer: start energy 0.23 vs 17.2 at 2 %, 0.48 vs 15.0 at 0.5 %
    # (measured); bound 10x lower
    assert on.energy_history[0] < 0.1 * off.energy_history[0], (on.energy_history[0], off.energy_history[0])
    # both end at the same minimum (final energies within 0.1 %)
    assert abs(on.energy_history[-1] - off.energy_history[-1]) < 1e-3 * off.energy_history[-1]
    # "auto": the coarse pass exactly when block matching's global strain exceeds the threshold
    big = off.blockmatch.global_strain() > COARSE_TO_FINE_STRAIN
    assert big == (strain > COARSE_TO_FINE_STRAIN)                          # measured 0.0198 and 0.0049
    assert np.array_equal(auto.u, (on if big else off).u) and (("coarse_pass" in auto.timings) == big)


def _field(scale):
    def u(p):
        x, y = p[:, 0], p[:, 1]
        return scale * np.column_stack([-0.01 * x + 0.02 * np.sin(2 * np.pi * x / 24.0),
                                        0.005 * (y - 8.0) + 0.004 * np.cos(2 * np.pi * y / 24.0)])
    return u


def test_track_grid_reference_registers_on_the_frame_0_grid():
    """grid="reference" minimises the literal eq:IR, I_k(x + S_k) against I_{k+1}(x + S_{k+1}) on the frame-0
    pixel grid: the NCC each frame reports is that one, computed here from the images and the result alone;
    grid="current" samples frame k's own grid (another NCC) once the mesh has moved."""
    spacing, shape = (0.05, 0.2), (400, 80)
    f0 = speckle_image(shape, spacing, np.random.default_rng(3))
    scales = [0.0, 0.4, 0.9, 1.3]
    frames = np.stack([f0] + [warp_image(f0, spacing, (0, 0), _field(s)) for s in scales[1:]])
    kw = dict(spacing=spacing, regularizer="strain", alpha=3.0, element_size=1.0, margin=1.0)
    X, Y = np.meshgrid(*pixel_axes(shape, spacing, (0.0, 0.0)), indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])
    images = [SplineImage(f, spacing) for f in frames]
    gap = {}
    for grid in ("reference", "current"):
        seq = femreg.track(frames, grid=grid, **kw)
        assert seq.flags == ["", "", ""], seq.flags
        S0 = np.zeros_like(pts)
        gap[grid] = []
        for k, res in enumerate(seq, start=1):
            S1 = res.displacement(pts)                  # frame 0 -> k, NaN outside the frame-0 mesh
            ok = np.isfinite(S1).all(axis=1)
            literal = np.corrcoef(images[k - 1](pts[ok] + S0[ok]), images[k](pts[ok] + S1[ok]))[0, 1]
            gap[grid].append(abs(res.ncc_after - literal))
            d = res.displacement(res.mesh.p.T) - _field(scales[k])(res.mesh.p.T)
            # measured (reference grid) at most 0.0030 / 0.013 mm RMS; bounds 0.2 and 0.15 pixels (0.01, 0.03)
            ex, ey = np.sqrt(np.mean(d ** 2, axis=0))
            assert ex < 0.2 * spacing[0] and ey < 0.15 * spacing[1], (grid, k, ex, ey)
            S0 = S1
    # measured: 4e-16 on every frame (reference); 4e-16 on frame 1 (S = 0: the same) and 0.017-0.018 after
    assert max(gap["reference"]) < 1e-9, gap
    assert gap["current"][0] < 1e-9 and min(gap["current"][1:]) > 1e-3, gap
