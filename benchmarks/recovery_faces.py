"""Strain recovery at the faces of shear bands: the recoveries of :mod:`femreg.fields` and two piecewise variants,
scored on the same R_P_sigma registrations of the band, inclusion, robustness and layer benchmarks.

One registration per pair (``femreg.register`` defaults), cached in ``--cache`` (a pickle per pair: the
displacement field does not depend on the recovery); each strain below is evaluated from its displacement and scored
with the robustness benchmark's total strain error (:func:`benchmarks.robustness.errors`, ``e``) and its e_xy part
(relative L2 of e_xy alone, ``exy``) over the benchmark's ROI:

* ``default``: what femreg reports (:meth:`femreg.result.RegistrationResult.on_grid`, the adaptive recovery with
  the result's :attr:`recovery_weight`);
* ``element``: the raw element gradient (``strain="element"``);
* ``average``, ``projection``, ``edge``: :func:`femreg.fields.recovered_strains` of that method;
* ``edge t0``: :func:`femreg.fields.edge_aware_strains` with ``tangential=0`` (each edge judged on its own);
* ``split centre``: the default recovery, but inside every element the refinement split (axial or lateral size
  below 3/4 of the base mesh's) the element-centre strain, constant over the element;
* ``split element``: the default recovery, but inside split elements the element gradient (``strain="element"``).

Suites: ``bands`` (:mod:`benchmarks.shear_bands`), ``inclusions`` (:mod:`benchmarks.inclusion_sizes`),
``robustness`` (:mod:`benchmarks.robustness`, seed 0, the sequence pair left out), ``layers``
(:mod:`benchmarks.layer_edges`).

Run: ``python benchmarks/recovery_faces.py [--suites bands,inclusions] [--cases WORDS] [--cache DIR]``; prints a
Markdown table (per pair: the default's projection weight ``w``, the fraction of
split elements, for a band the distance of its faces to the nearest row of mesh nodes; per strain: ``e`` /
``exy`` error, %, ``-`` where the truth has no e_xy) and per strain the change of ``e`` against the
default: mean over the band pairs and the largest rise over all pairs.
"""
from __future__ import annotations

import argparse
import os
import pickle
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.robustness import errors, make_data, roi_slices, truth  # noqa: E402

STRAINS = ("default", "element", "average", "projection", "edge", "edge t0", "split centre", "split element")
SUITES = ("bands", "inclusions", "robustness", "layers")


def suite_cases(suite):
    if suite == "bands":
        from benchmarks.shear_bands import CASES
    elif suite == "inclusions":
        from benchmarks.inclusion_sizes import CASES
    elif suite == "layers":
        from benchmarks.layer_edges import CASES
    else:
        from benchmarks.robustness import CASES
    return [c for c in CASES if not getattr(c, "sequence", None)]


def registration(case, data, cache: Path | None):
    """R_P_sigma defaults on ``data``; pickled in ``cache`` by case name."""
    import femreg

    path = None if cache is None else cache / f"{case.name}.pkl"
    if path is not None and path.is_file():
        with open(path, "rb") as fh:
            return pickle.load(fh)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = femreg.register(data.ref, data.mov, spacing=data.spacing, origin=data.origin)
    if path is not None:
        cache.mkdir(parents=True, exist_ok=True)
        try:
            with open(path, "wb") as fh:
                pickle.dump(res, fh)
        except Exception as exc:  # noqa: BLE001  a result that does not pickle is only not cached
            print(f"{case.name}: not cached ({exc})", file=sys.stderr)
            path.unlink(missing_ok=True)
    return res


def split_elements(res) -> np.ndarray:
    """Elements (bool, n_el) the refinement split: axial or lateral size below 3/4 of the base mesh's
    (``res.refinement.base_size``; without one, of the largest element's)."""
    c = np.asarray(res.mesh.p, float)[:, np.asarray(res.mesh.t)]
    h = c.max(axis=1) - c.min(axis=1)                                # (2, n_el) mm
    base = getattr(getattr(res, "refinement", None), "base_size", None)
    base = h.max(axis=1) if base is None else np.asarray(base, float)
    return np.any(h < 0.75 * base[:, None], axis=0)


def strain_grids(res) -> dict:
    """{strain: pixel-grid fields} of one registration (module docstring)."""
    from femreg.fields import edge_aware_strains, element_strains
    from femreg.sampling import sample_grid

    p, t, u = res.mesh.p, res.mesh.t, res.u
    out = {"default": res.on_grid(), "element": res.on_grid("element")}
    for m in ("average", "projection", "edge"):
        out[m] = res.on_grid(recovery=m)
    out["edge t0"] = res._masked_grid(sample_grid(u, res.locator, res.pixel_grid, "recovered",
                                                  nodal_strain=edge_aware_strains(p, t, u, tangential=0)))
    split = split_elements(res)
    nodal = np.asarray(res.nodal_strain, float)
    corners = nodal[np.asarray(t)]                                   # (4, n_el, 3)
    corners[:, split] = element_strains(p, t, u)[split][None]
    out["split centre"] = res._masked_grid(sample_grid(u, res.locator, res.pixel_grid, "recovered",
                                                       nodal_strain=corners))
    # per pixel: whether its element was split (the element strain there, the default elsewhere)
    loc = res.locator.locate_grid(*res.pixel_grid.axes())
    in_split = np.zeros(res.pixel_grid.shape[0] * res.pixel_grid.shape[1], bool)
    in_split[loc.inside] = split[loc.element]
    in_split = in_split.reshape(res.pixel_grid.shape)
    out["split element"] = {k: (np.where(in_split, out["element"][k], out["default"][k])
                                if k in ("exx", "eyy", "exy") else out["default"][k]) for k in out["default"]}
    return out


def score_case(case, cache):
    from forward.pairs import PROBES

    data = make_data(case)
    res = registration(case, data, cache)
    sl = roi_slices(data.ref.shape, data.spacing)
    tr = truth(data, case, sl)
    lam = PROBES[case.probe].wavelength_mm
    row = {"case": case.name, "weight": float(res.recovery_weight),
           "split": float(np.mean(split_elements(res))),
           "faces": face_offsets(res, data.field) if hasattr(data.field, "thickness_mm") else None}
    for s, g in strain_grids(res).items():
        err = errors(g, tr, sl, lam)
        ex = np.nan_to_num(np.asarray(g["exy"], float)[sl], nan=0.0)
        den = float(np.sum(tr["exy"] ** 2))
        # no e_xy in the truth (uniform compression, layers): no relative e_xy error
        rel = float(np.sqrt(np.sum((ex - tr["exy"]) ** 2) / den)) if den > 1e-6 * np.sum(tr["exx"] ** 2) else np.nan
        row[s] = (100 * err["e"], 100 * rel)
    return row


def face_offsets(res, band) -> tuple[float, float]:
    """Distance (mm) of the band's upper and lower faces to the nearest row of mesh nodes."""
    xs = np.unique(np.asarray(res.mesh.p, float)[0])
    faces = (band.depth_mm - band.thickness_mm / 2, band.depth_mm + band.thickness_mm / 2)
    return tuple(float(np.min(np.abs(xs - f))) for f in faces)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suites", default=",".join(SUITES))
    ap.add_argument("--cases", default="", help="comma-separated words; run cases whose name contains one")
    ap.add_argument("--cache", default="out/recovery_faces/cache")
    a = ap.parse_args(argv)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(v, "1")
    words = [w for w in a.cases.split(",") if w]
    cache = Path(a.cache) if a.cache else None
    print("each cell: total strain error % / e_xy error %\n\n| suite | pair | w | split | faces mm | " + " | ".join(STRAINS)
          + " |\n" + "|---" * (len(STRAINS) + 5) + "|", flush=True)
    rows = []
    for suite in [s for s in a.suites.split(",") if s]:
        if suite not in SUITES:
            print(f"unknown suite {suite!r}; one of {SUITES}", file=sys.stderr)
            return 2
        for case in suite_cases(suite):
            if words and not any(w in case.name for w in words):
                continue
            r = score_case(case, cache)
            r["suite"] = suite
            rows.append(r)
            faces = "" if r["faces"] is None else " / ".join(f"{v:.3f}" for v in r["faces"])
            print(f"| {suite} | {r['case']} | {r['weight']:.2f} | {r['split']:.2f} | {faces} | "
                  + " | ".join(f"{r[s][0]:.1f} / " + ("-" if np.isnan(r[s][1]) else f"{r[s][1]:.1f}")
                               for s in STRAINS) + " |", flush=True)
    print()
    bands = [r for r in rows if r["suite"] == "bands"]
    for s in STRAINS[1:]:
        d = np.array([r[s][0] - r["default"][0] for r in rows])
        worst = rows[int(np.argmax(d))] if rows else None
        mb = np.mean([r[s][0] - r["default"][0] for r in bands]) if bands else float("nan")
        print(f"{s:14s}: band pairs mean {mb:+.2f} points; largest rise {np.max(d):+.2f} ({worst['case']}); "
              f"pairs worse by > 0.1: {int(np.sum(d > 0.1))} of {len(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
