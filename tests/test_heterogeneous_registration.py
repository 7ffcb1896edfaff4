"""Registration defaults on heterogeneous tissue (forward.tissue), a field no default was chosen on."""
import numpy as np
import pytest

import femreg
from forward.pairs import make_pair
from forward.tissue import RandomTissue


@pytest.mark.parametrize("seed, bound", [(21, 0.16), (23, 0.17)])
def test_defaults_follow_heterogeneous_tissue(seed, bound):
    # measured: total strain error 0.130 (seed 21) / 0.139 (seed 23), NCC block matching 0.726 / 0.716;
    # bounds about 1.2x the measured value; the uniform field of the true mean strain (all a homogeneous
    # model can give: 0.328 / 0.417) must be at least twice as far
    from benchmarks.robustness import errors, roi_slices

    f = RandomTissue(seed, 0.01, "plane-stress", sigma=0.7, corr_mm=2.0, size_mm=(30.0, 30.0))
    p = make_pair(f, "L7", (20.0, 20.0), snr_db=25.0, seed=seed, top_mm=3.0)
    sl = roi_slices(p.ref.shape, p.spacing)
    ii = np.arange(sl[0].start, sl[0].stop, sl[0].step)
    jj = np.arange(sl[1].start, sl[1].stop)
    X, Y = np.meshgrid(p.origin[0] + ii * p.spacing[0], p.origin[1] + jj * p.spacing[1], indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel()])
    u, e = f.displacement(P), f.strain(P)
    t = {k: v.reshape(X.shape) for k, v in
         dict(ux=u[:, 0], uy=u[:, 1], exx=e[:, 0], eyy=e[:, 1], exy=e[:, 2]).items()}
    r = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    assert r.success, r.message
    err = errors(r.on_grid(), t, sl, 0.2)["e"]
    full = {k: np.full(p.ref.shape, np.nan) for k in t}
    for k in t:
        full[k][sl] = np.mean(t[k])
    uniform = errors(full, t, sl, 0.2)["e"]
    assert err < bound
    assert err < 0.5 * uniform


def test_refined_result_says_when_the_speckle_decorrelates(tmp_path, capsys):
    # an independent speckle frame mixed into the moving one (out-of-plane motion): median element NCC 0.87
    # (measured on this L7 pair at rho 0.5), below femreg.refine.DECORRELATED_NCC; the clean pair 0.99
    from forward import fields as F

    f = RandomTissue(31, 0.01, "plane-stress", sigma=0.7, corr_mm=2.0)
    p = make_pair(f, "L7", (30.0, 30.0), snr_db=25.0, seed=31, top_mm=3.0)
    q = make_pair(F.compression(0.0), "L7", (30.0, 30.0), snr_db=None, seed=131, top_mm=3.0)
    rho = 0.5
    mov = np.sqrt(1 - rho ** 2) * p.mov + rho * q.ref * np.std(p.mov) / np.std(q.ref)
    clean = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    noisy = femreg.register(p.ref, mov, spacing=p.spacing, origin=p.origin)
    assert clean.refinement.passes and noisy.refinement.passes        # both refined
    assert "decorrelated" not in clean.message
    assert "speckle is decorrelated (median element NCC 0.8" in noisy.message, noisy.message
    # the command line says it on a line of its own, in its own words
    from femreg.cli import main

    np.savez(tmp_path / "pair.npz", frames=np.stack([p.ref, mov]).astype(np.float32), spacing=np.array(p.spacing))
    assert main(["register", str(tmp_path / "pair.npz"), "-o", str(tmp_path / "r.npz")]) == 0
    out = capsys.readouterr().out
    assert "femreg register: note: refined although the speckle is decorrelated" in out
    assert "against --refine none" in out
