"""Bit-identity of ``femreg.register`` / ``femreg.track`` / ``femreg.elastogram`` across a change of their staging:
saves every array and text of their results on a few loops, and compares two such files (``np.array_equal``).

Loops: the TGC loop of ``benchmarks/track_tgc.py`` (L12, cut at depth where frames 0 and 1 do not match), a plain
simulated linear loop (nothing cut), a convex loop whose recording stops at 3/4 of the range (a level cut, said
along the rays), a convex pair with dead rays at one side and one with a given depth (the lateral and the given
crop's texts).

Run: ``PYTHONPATH=OLD python benchmarks/staging_identity.py save old.npz``, the same with the new tree, then
``python benchmarks/staging_identity.py compare old.npz new.npz`` (exit 1 on a difference).  About 1-2 min a save on
one core (``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1``).

Measured (2026-12-07): the search staged before the pyramid's coarse solve, noise_at_depth run as register up to its
decision, track / elastogram taking the first pair's search from it, and the echo cuts as data against the code
before them: 110 arrays compared, none differs.
"""
from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))      # after PYTHONPATH: it chooses the femreg measured
sys.path.append(str(ROOT / "benchmarks"))


def _result(out: dict, key: str, r) -> None:
    out[f"{key}.u"] = np.asarray(r.u)
    out[f"{key}.p"] = np.asarray(r.mesh.p)
    out[f"{key}.t"] = np.asarray(r.mesh.t)
    out[f"{key}.quality"] = np.asarray(r.quality if r.quality is not None else [])
    out[f"{key}.ncc"] = np.array([r.ncc_before, r.ncc_after])
    out[f"{key}.text"] = np.array(json.dumps(dict(message=r.message, excluded=getattr(r, "excluded", None),
                                                  success=bool(r.success), nit=int(r.nit),
                                                  roi=None if getattr(r, "roi", None) is None else list(r.roi))))
    dm = getattr(r, "data_mask", None)
    out[f"{key}.data_mask"] = np.asarray(dm if dm is not None else [])


def _track(out: dict, key: str, seq) -> None:
    for k, r in enumerate(seq, start=1):
        _result(out, f"{key}[{k}]", r)
    out[f"{key}.flags"] = np.array(json.dumps([str(f) for f in seq.flags]))


def _elastogram(out: dict, key: str, e) -> None:
    out[f"{key}.exx"] = np.asarray(e.exx)
    out[f"{key}.text"] = np.array(json.dumps(dict(region=None if e.region is None else np.asarray(e.region).tolist(),
                                                  excluded=e.excluded, n_usable=int(e.n_usable),
                                                  ref_frame=int(e.ref_frame)), default=repr))
    out[f"{key}.pairs"] = np.array(json.dumps(list(e.pairs), default=repr))


def save(path: str) -> None:
    import femreg
    from femreg import Convex
    from femreg.elastogram import elastogram
    from forward import fields as F
    from forward.beam import make_beam_pair, make_beam_sequence
    from forward.pairs import make_sequence
    from track_tgc import tgc_loop

    out = {}
    print(f"femreg from {Path(femreg.__file__).parent}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        s, _ = tgc_loop("L12", 0)
        plain = make_sequence(F.Inclusion("stiff", "plane-strain", 0.01, radius_mm=3.0), "L12", (16.0, 12.0), 30.0,
                              1, n_frames=4, step=0.01)
        for name, q in (("tgc", s), ("plain", plain)):
            kw = dict(spacing=q.spacing, origin=q.origin)
            _result(out, f"{name}.register", femreg.register(q.frames[0], q.frames[1], **kw))
            _track(out, f"{name}.track", femreg.track(q.frames, **kw))
            _elastogram(out, f"{name}.elastogram", elastogram(q.frames, **kw))
            print(name, "done")
        conv = make_beam_sequence(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                                  depth_mm=16.0, n_rays=40, snr_db=30.0, seed=2, n_frames=4, step=0.008)
        frames = conv.frames.copy()
        frames[:, 3 * frames.shape[1] // 4:] = 0.0
        kw = dict(spacing=conv.spacing[0], origin=conv.origin, geometry=conv.geometry)
        _result(out, "convex.register", femreg.register(frames[0], frames[1], maxiter=3, **kw))
        _track(out, "convex.track", femreg.track(frames, maxiter=3, **kw))
        _elastogram(out, "convex.elastogram", elastogram(frames, **kw))
        p = make_beam_pair(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                           depth_mm=16.0, n_rays=40, snr_db=30.0, seed=1)
        ref, mov = p.ref.copy(), p.mov.copy()
        ref[:, :6] = 0.0
        mov[:, :6] = 0.0
        kw = dict(spacing=p.spacing, origin=p.origin, geometry=p.geometry, maxiter=2)
        _result(out, "convex_rays.register", femreg.register(ref, mov, **kw))
        _result(out, "convex_depth.register", femreg.register(p.ref, p.mov, depth=(p.origin[0] + 3.0,
                                                                                   p.origin[0] + 12.0), **kw))
        print("convex done")
    np.savez(path, **out)
    for k in sorted(out):
        if k.endswith(".text"):
            print(k, str(out[k])[:300])


def compare(a: str, b: str) -> int:
    with np.load(a) as za, np.load(b) as zb:
        keys = sorted(set(za.files) | set(zb.files))
        bad = [k for k in keys if k not in za.files or k not in zb.files
               or not np.array_equal(za[k], zb[k], equal_nan=za[k].dtype.kind == "f")]
    print(f"{len(keys)} arrays compared, {len(bad)} differ" + (": " + ", ".join(bad) if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    if sys.argv[1] == "save":
        save(sys.argv[2])
    else:
        sys.exit(compare(sys.argv[2], sys.argv[3]))
