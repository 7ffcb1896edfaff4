"""register and track end to end with the compiled loops (femreg._kernels) on and off.

The numpy twins must give the same numbers stage by stage (speckle statistics, initial guess, every Gauss-Newton
iterate, the check's maps, the result grids) to 1e-10, and therefore the same decisions (iterations, stopping
rule, repairs, success, flags), on pairs whose decisions are not marginal: no step within 10 % of the stopping
tolerance, a peak-hopping jump of a whole RF period.  With the loops off no compiled loop may run at all."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import femreg
from femreg import _kernels, pyramid
from femreg.registration import component_tol
from femreg.synthetic import speckle_image, speckle_pair, warp_image

needs_numba = pytest.mark.skipif(_kernels._numba is None, reason="numba not installed: no compiled loops")
pytestmark = needs_numba

SP = (0.025, 0.2)
SHAPE = (600, 80)                      # 15 x 16 mm
REL = 1e-10                            # stage-by-stage agreement (measured: 3e-14 on u, 2e-14 on the energies)
# loops that other loops call (compiled together with them), not entry points
_INNER = ("cubic_point", "_cubic_weights")


def compression(e):
    return lambda p: np.column_stack([-e * p[:, 0], 0.5 * e * (p[:, 1] - 8.0)])


@pytest.fixture
def calls(monkeypatch):
    """Count the calls of every compiled entry point, wherever femreg looks it up."""
    count = {}
    mods = [m for name, m in list(sys.modules.items()) if name.startswith("femreg") and m is not None]
    for name in dir(_kernels):
        f = getattr(_kernels, name)
        if not hasattr(f, "py_func") or name in _INNER:
            continue

        def wrap(*a, _f=f, _n=name, **k):
            count[_n] = count.get(_n, 0) + 1
            return _f(*a, **k)

        for m in mods:
            if getattr(m, name, None) is f:
                monkeypatch.setattr(m, name, wrap)
    return count


def _close(a, b, what):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, what
    assert np.array_equal(np.isnan(a), np.isnan(b)), what
    scale = max(np.nanmax(np.abs(a)) if a.size else 0.0, 1e-300)
    err = np.nanmax(np.abs(a - b)) if a.size else 0.0
    assert err <= REL * scale, f"{what}: {err:.3g} relative to {scale:.3g}"


def _register_stages(ref, mov, **kw):
    """The stages of one register call: statistics, the initial guess (maxiter=0), every iterate of the solve,
    the result and its grids."""
    stats = pyramid.speckle_statistics(femreg.image.normalize_pair(ref, mov)[0], SP)
    start = femreg.register(ref, mov, spacing=SP, maxiter=0, **kw)
    iterates = []
    res = femreg.register(ref, mov, spacing=SP, callback=lambda u, info: iterates.append((u.copy(), info)), **kw)
    grids = (res.on_grid(), res.on_grid("element"))
    return stats, start, iterates, res, grids


def _compare_register(on, off):
    (s1, g1, it1, r1, G1), (s0, g0, it0, r0, G0) = on, off
    _close([s1.period, *s1.cell], [s0.period, *s0.cell], "speckle statistics")
    _close(g1.u, g0.u, "initial guess")
    # the callback sees the first solve (a repair solves again): the same iterations in both
    assert len(it1) == len(it0) and r1.nit == r0.nit
    for (u1, i1), (u0, i0) in zip(it1, it0):
        _close(u1, u0, f"iterate {i1['nit']}")
        _close([i1["energy"], i1["rel_change"]], [i0["energy"], i0["rel_change"]], f"iterate {i1['nit']}")
        assert i1["step"] == i0["step"]                                    # same line-search decision
    _close(r1.u, r0.u, "result")
    _close(r1.energy_history, r0.energy_history, "energies")
    _close(r1.quality, r0.quality, "quality map")
    _close(r1.hop_gain, r0.hop_gain, "peak-hopping map")
    _close([r1.ncc_before, r1.ncc_after], [r0.ncc_before, r0.ncc_after], "NCC")
    for a, b in zip(G1, G0):
        for k in a:
            _close(a[k], b[k], f"grid {k}")
    assert (r1.success, r1.status, r1.message) == (r0.success, r0.status, r0.message)


def _not_marginal(stages, tol=1e-3):
    """No Gauss-Newton step within 10 % of the stopping tolerance (a round-off difference cannot flip it)."""
    _, start, iterates, _, _ = stages
    t = component_tol(tol, start.u)
    for _, info in iterates:
        assert abs(info["rel_change"] / t - 1.0) > 0.1, (info, t)


@pytest.fixture(scope="module")
def pair():
    return speckle_pair(compression(0.02), SHAPE, SP, seed=3, snr_db=30)


def test_register_is_the_same_with_and_without_the_compiled_loops(pair, calls):
    ref, mov = pair
    with _kernels.compiled(True):
        on = _register_stages(ref, mov)
    used = set(calls)
    calls.clear()
    with _kernels.compiled(False):
        off = _register_stages(ref, mov)
    assert not calls, f"compiled loops ran with the switch off: {sorted(calls)}"
    # the run goes through the compiled stages it compares: warp, gradient, Hessians, pyramid, check, grids
    assert {"warp_grid", "gradient_grid", "hessian_rows", "gram_into_pattern", "spline_coefficients",
            "hilbert_half_spectrum", "box_sums", "block_ncc", "block_energies", "grid_fields",
            "grid_values", "outside_grid"} <= used, sorted(used)
    _not_marginal(on)
    assert on[3].success and on[3].nit >= 2
    _compare_register(on, off)


def test_repair_decisions_are_the_same_with_and_without_the_compiled_loops(pair):
    ref, mov = pair
    with _kernels.compiled(True):
        good = femreg.register(ref, mov, spacing=SP)
    period = pyramid.speckle_statistics(femreg.image.normalize_pair(ref, mov)[0], SP).period
    p = good.mesh.p
    start = good.u.copy()
    patch = (np.abs(p[0] - 7.5) < 1.5) & (np.abs(p[1] - 8.0) < 2.0)       # a few interior nodes
    assert 2 <= patch.sum() <= 12, patch.sum()
    start[0::2][patch] += period                                           # a whole RF period off: no margin case
    out = {}
    for flag in (True, False):
        with _kernels.compiled(flag):
            out[flag] = _register_stages(ref, mov, initial=start)
    assert "reseeded" in out[True][3].message, out[True][3].message         # the repair ran
    _compare_register(out[True], out[False])


def _field(scale):
    def u(p):
        x, y = p[:, 0], p[:, 1]
        return np.column_stack([scale * (-0.01 * x + 0.02 * np.sin(2 * np.pi * x / 24.0)),
                                scale * (0.005 * (y - 8.0) + 0.004 * np.cos(2 * np.pi * y / 24.0))])
    return u


@pytest.mark.parametrize("grid", ["current", "reference"])
def test_track_is_the_same_with_and_without_the_compiled_loops(grid, calls):
    spacing = (0.05, 0.2)
    f0 = speckle_image((400, 80), spacing, np.random.default_rng(3))
    frames = np.stack([f0] + [warp_image(f0, spacing, (0, 0), _field(s)) for s in (0.4, 0.9, 1.3)])
    out = {}
    for flag in (True, False):
        calls.clear()
        with _kernels.compiled(flag):
            steps = []
            seq = femreg.track(frames, spacing=spacing, grid=grid,
                               callback=lambda u, info: steps.append(info["rel_change"]))
            out[flag] = (seq, steps)
        if flag and grid == "current":     # the moved mesh: point location walk, per-node warp, element Hessian
            assert {"walk_kernel", "warp_nodes", "gradient_nodes", "element_blocks"} <= set(calls), sorted(calls)
    assert not calls, f"compiled loops ran with the switch off: {sorted(calls)}"
    (s1, st1), (s0, st0) = out[True], out[False]
    assert s1.flags == s0.flags == ["", "", ""]
    _close(st1, st0, "Gauss-Newton steps")
    for k, (a, b) in enumerate(zip(s1, s0)):
        assert (a.nit, a.status, a.success, a.message) == (b.nit, b.status, b.success, b.message), k
        _close(a.u, b.u, f"frame {k + 1}")
        _close(a.energy_history, b.energy_history, f"frame {k + 1} energies")
        _close(a.quality, b.quality, f"frame {k + 1} quality")
    _close(np.asarray(s1.increments), np.asarray(s0.increments), "increments")


def test_switch_restores_and_environment_turns_the_loops_off(monkeypatch):
    monkeypatch.delenv(_kernels.ENV_SWITCH, raising=False)
    before = _kernels.use_compiled()
    code = ("import sys; from femreg import _kernels; "
            "print(_kernels.use_compiled(), 'numba' in sys.modules)")
    root = str(Path(__file__).resolve().parents[1])

    def child(**env):
        env = dict(os.environ, PYTHONPATH=root, **env)
        return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                              check=True).stdout.split()

    with _kernels.compiled(False) as on:
        assert on is False and not _kernels.use_compiled()
        assert child() == ["False", "False"]          # started processes inherit the switch (numba not imported)
        with _kernels.compiled(True):
            assert _kernels.use_compiled()
        assert not _kernels.use_compiled()
    assert _kernels.use_compiled() == before and _kernels.ENV_SWITCH not in os.environ
    assert child(FEMREG_NUMBA="1") == ["True", "True"]
