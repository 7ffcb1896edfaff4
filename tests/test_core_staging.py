"""register is the one orchestrator of its stages: femreg.registration.noise_at_depth runs register itself up to its
noise-at-depth decision, and track / elastogram register their first pair from the start that decision made
(femreg.registration.sharing_start) instead of searching it again.  An echo region's cut is data
(femreg.echo.Cut): its sentence, and a convex frame's (femreg.geometry.beam_excluded), are built from it."""
import warnings

import numpy as np
import pytest

import femreg
import femreg.initial
from femreg.echo import find_echo, unmatched_crop
from femreg.elastogram import elastogram
from femreg.registration import noise_at_depth
from forward import fields as F
from forward.pairs import PROBES, alpha_for_floor, attenuation_gain_db, make_pair, make_sequence

SNR, TOP = 30.0, 2.0


@pytest.fixture(scope="module")
def plain_loop():
    """3 frames of 12 MHz RF, 12 x 10 mm, echo to the bottom (nothing to cut), 1 % compression per frame."""
    return make_sequence(F.compression(0.01), "L12", (12.0, 10.0), SNR, 3, n_frames=3, step=0.01, top_mm=TOP)


def _count_searches(monkeypatch):
    """{(shape, content digest) of the reference the pyramid searched: calls} for every search from here on."""
    seen = {}
    search = femreg.initial.pyramid_search

    def counting(a, b, *args, **kw):
        key = (np.shape(a), hash(np.ascontiguousarray(a).tobytes()), hash(np.ascontiguousarray(b).tobytes()))
        seen[key] = seen.get(key, 0) + 1
        return search(a, b, *args, **kw)

    monkeypatch.setattr(femreg.initial, "pyramid_search", counting)
    return seen


@pytest.mark.parametrize("run", ["track", "elastogram"])
def test_the_first_pair_is_searched_once(plain_loop, monkeypatch, run):
    # before: noise_at_depth ran register's stages on frames 0 and 1 (validate, images, mesh, the pyramid with its
    # coarse solve) and the loop's registration of that pair ran them again: 2 searches of the same frames
    s = plain_loop
    seen = _count_searches(monkeypatch)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if run == "track":
            out = femreg.track(s.frames, spacing=s.spacing, origin=s.origin, maxiter=3)
            assert out[0].excluded is None
        else:
            out = elastogram(s.frames, spacing=s.spacing, origin=s.origin, maxiter=3)
            assert out.region is None and any(r["ref"] == 0 and r["mov"] == 1 for r in out.pairs), out.pairs
    assert sum(seen.values()) >= 1, "the counter saw no search"
    assert max(seen.values()) == 1, f"a pair searched {max(seen.values())} times: {list(seen.values())}"


def test_the_workers_path_shares_the_first_search(plain_loop, monkeypatch):
    # the pairs registered on Dask workers: the first run's first pair took the cut decision's search only in the
    # caller's process (a worker does not see its context), so frames 0 and 1 were searched twice.  One worker of
    # threads runs the workers path in this process (the counter sees it) on one run of pairs: the same order of
    # warm starts as workers=1, so the same arrays
    distributed = pytest.importorskip("distributed")
    s = plain_loop
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        one = elastogram(s.frames, spacing=s.spacing, origin=s.origin, maxiter=3)
        seen = _count_searches(monkeypatch)
        with distributed.Client(processes=False, n_workers=1, threads_per_worker=1,
                                dashboard_address=None) as client:
            pool = elastogram(s.frames, spacing=s.spacing, origin=s.origin, maxiter=3, client=client)
    assert sum(r["registered"] for r in pool.pairs) >= 2, pool.pairs      # the workers path (more than one pair)
    assert sum(seen.values()) >= 1, "the counter saw no search"
    assert max(seen.values()) == 1, f"a pair searched {max(seen.values())} times: {list(seen.values())}"
    for name in ("exx", "quality", "cine"):
        assert np.array_equal(getattr(one, name), getattr(pool, name), equal_nan=True), name
    assert [r["strain"] for r in one.pairs] == [r["strain"] for r in pool.pairs]


def test_noise_at_depth_stops_at_the_decision(plain_loop, monkeypatch):
    # register runs up to its decision and no further: no Gauss-Newton (neither the pyramid's coarse solve nor the
    # final one), and the decision is the one register makes on the pair
    import femreg.pyramid
    import femreg.registration

    s = plain_loop
    solves = []
    monkeypatch.setattr(femreg.pyramid, "gauss_newton", lambda *a, **k: solves.append(1))
    monkeypatch.setattr(femreg.registration, "solve", lambda *a, **k: solves.append(2))
    assert noise_at_depth(s.frames[0], s.frames[1], spacing=s.spacing, origin=s.origin) is None
    assert not solves, solves


def test_the_crop_data_says_the_sentence():
    # a detected region (zero rows at the bottom, dead lines at the left) and the TGC noise cut: the sentence is the
    # cuts' text, and each cut's numbers are the region's edges
    p = make_pair(F.compression(0.01), "L7", (20.0, 15.0), SNR, 0, top_mm=TOP)
    ref, mov = p.ref.copy(), p.mov.copy()
    n, m = ref.shape
    ref[3 * n // 4:], mov[3 * n // 4:] = 0.0, 0.0
    ref[:, :8], mov[:, :8] = 0.0, 0.0
    region = find_echo(ref, mov, spacing=p.spacing, origin=p.origin)
    (dx, dy), (ox, oy) = p.spacing, p.origin
    assert region.excluded == "; ".join(c.text for c in region.cuts), (region.excluded, region.cuts)
    below = [c for c in region.cuts if c.side == "below"]
    left = [c for c in region.cuts if c.side == "left"]
    assert len(below) == 1 and len(left) == 1, region.cuts
    assert below[0].lo == ox + (region.rows[1] - 0.5) * dx and f"depth below {below[0].lo:.1f} mm" in region.excluded
    assert left[0].hi == oy + (region.cols[0] - 0.5) * dy and f"lines at {left[0].span} (left)" in region.excluded
    assert region.row_cuts == tuple(below), region.row_cuts

    pr = PROBES["L12"]
    gain = attenuation_gain_db(alpha_for_floor(15.0, SNR, pr.f0_mhz), pr.f0_mhz)
    q = make_pair(F.compression(0.01), "L12", (20.0, 12.0), SNR, 0, top_mm=TOP, echo_gain_db=gain,
                  tgc_db=lambda x: -gain(x))
    crop = noise_at_depth(q.ref, q.mov, spacing=q.spacing, origin=q.origin)
    assert crop is not None, "the TGC pair was not cut"
    (cut,) = crop.region.cuts
    assert crop.region.excluded == cut.text and cut.side == "below" and "do not match" in cut.why
    assert cut.lo == q.origin[0] + (crop.slices[0].stop - 0.5) * q.spacing[0]
    assert unmatched_crop(None, q.ref.shape, q.spacing, q.origin) is None


def test_beam_sentence_of_saturated_strips_is_in_the_probe_terms():
    # saturated strips were left in sample-space words by the rewriting ("depth a-b mm", "lines a-b mm" of arc)
    from femreg.echo import Cut, EchoRegion
    from femreg.geometry import beam_excluded

    sat = "excluded: saturated (more than 2% of the samples clipped; 0.5% of the frame)"
    cuts = (Cut("depth", None, 5.0, 7.5, sat), Cut("lines", None, 10.0, 12.0, sat),
            Cut("depth", "kept", 9.0, 9.5, "kept (inside the echo region)"))
    region = EchoRegion((0, 10), (0, 10), (10, 10), (1.0, 1.0), (0.0, 0.0), "; ".join(c.text for c in cuts),
                        cuts=cuts)
    assert region.excluded.startswith(f"depth 5.0-7.5 mm {sat}; lines 10.0-12.0 mm {sat}"), region.excluded
    rho = 40.0
    t = beam_excluded(region, rho)
    a0, a1 = np.rad2deg(10.0 / rho), np.rad2deg(12.0 / rho)
    assert t == (f"range 5.0-7.5 mm (along the rays) {sat}; rays at {a0:.1f} to {a1:.1f} deg {sat}; "
                 "saturated ranges at 9.0-9.5 mm (along the rays) kept (inside the echo region)"), t
    assert beam_excluded(region, rho, rows_only=True) == f"range 5.0-7.5 mm (along the rays) {sat}"
