"""The paper's closing hypothesis -- do SPREME-regularised displacements give better shear-modulus images? --
as a stand-alone run.  The scoring, the table and the conclusion live in :mod:`paperstudy.inversion` (the study
report's section); this script only finds or makes the displacements.

* ``--study DIR``: a finished study folder (``femreg study -o DIR``): invert its cases (nothing is registered).
* otherwise ``--out DIR`` becomes a small study folder: the registrations the hypothesis needs (3D HI / SI / mHI,
  every regulariser at femreg's default alphas, frames 1 -> 7 and accumulated to frame 20) are computed there by
  the study's own case runner (:func:`paperstudy.study.run_cases`, on :mod:`femreg.batch` / Dask), resuming what
  an earlier run left; about 40 min on 2 cores for the 24 cases.  ``--quick``: 3D HI, frames 1 -> 7 only.

Both write ``DIR/inversions/table.md`` (the section) and print it; rerunning recomputes nothing.

Usage: ``python benchmarks/inversion_hypothesis.py [--study DIR | --out DIR [--quick]] [--jobs 2]
[--scheduler ADDRESS] [--models plane-stress,plane-strain]``
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def make_study(out, *, quick=False, jobs=2, scheduler=None, progress=True):
    """Register the hypothesis' cases into ``out`` (a study folder: settings.json, alphas.json, cases/) at
    femreg's default alphas; returns the :class:`paperstudy.study.StudyResult`."""
    import forward
    from paperstudy.inversion import DATASETS, load_study
    from femreg.errors import InputError
    from paperstudy.study import (StudySettings, _atomic_write_json, _LazyClient, _parse_dataset, make_case,
                                  read_default_alphas, run_cases, write_default_alphas)

    datasets = ("3d-HI",) if quick else DATASETS
    alphas = read_default_alphas()
    s = StudySettings.full(sweep_datasets=datasets, single_datasets=datasets, track_datasets=() if quick
                           else datasets, alphas={r: alphas[r] for r in StudySettings().regularizers},
                           name="inversion-hypothesis" + ("-quick" if quick else ""))
    s.validate()
    out = Path(out)
    if (out / "settings.json").exists():
        import json

        if json.loads((out / "settings.json").read_text()) != s.to_dict():
            raise InputError(f"{out} holds a study with other settings: pass it as --study {out}")
    out.mkdir(parents=True, exist_ok=True)
    _atomic_write_json(out / "settings.json", s.to_dict())
    write_default_alphas(s.alphas, out / "alphas.json", settings=s)
    for d in datasets:       # generate (or load) each sequence once here, so the workers only read the cache
        m, i = _parse_dataset(d)
        forward.get_sequence(m, i, seed=s.seed, snr_db=s.snr_db, n_frames=s.n_frames, **s.sequence_options)
    specs = [make_case(s, "track", d, r, s.alphas[r], s.n_track_frames) for d in s.track_datasets
             for r in s.regularizers]
    specs += [make_case(s, "pair", d, r, s.alphas[r], s.pair) for d in s.single_datasets for r in s.regularizers]
    t0 = time.perf_counter()
    client = _LazyClient(None, jobs, scheduler)     # a Dask cluster only if something is left to register
    try:
        run_cases(specs, out, jobs=jobs, client=client, progress=progress, desc="registrations")
    finally:
        client.close()
    print(f"registrations: {time.perf_counter() - t0:.0f} s")
    res = load_study(out)
    res.runs = [{"jobs": jobs, "scheduler": scheduler}]
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study", help="a finished study folder: invert its cases, register nothing")
    ap.add_argument("--out", default=str(REPO / "out" / "inversion_hypothesis"),
                    help="folder for the registrations when there is no --study (default out/inversion_hypothesis)")
    ap.add_argument("--quick", action="store_true", help="without --study: 3D HI, frames 1 -> 7 only")
    ap.add_argument("--jobs", type=int, default=2, help="local Dask worker processes (1 = in this process)")
    ap.add_argument("--scheduler", help="a running Dask scheduler's address instead of local processes")
    ap.add_argument("--models", default="plane-stress,plane-strain", help="inversion models, comma-separated")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    from femreg.errors import InputError
    from paperstudy.inversion import MODELS, hypothesis_section, load_study

    models = tuple(m.strip() for m in args.models.split(",") if m.strip())
    if not models or any(m not in MODELS for m in models):
        raise InputError(f"--models must be from {MODELS}, got {args.models!r}")
    if args.jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {args.jobs}")
    t0 = time.perf_counter()
    if args.study:
        res = load_study(args.study)
        res.runs = [{"jobs": args.jobs, "scheduler": args.scheduler}]
    else:
        res = make_study(args.out, quick=args.quick, jobs=args.jobs, scheduler=args.scheduler,
                         progress=not args.no_progress)
    lines = hypothesis_section(res, models=models, progress=not args.no_progress)
    path = Path(res.outdir) / "inversions" / "table.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"{time.perf_counter() - t0:.0f} s; wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
