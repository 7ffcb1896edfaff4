"""``femreg study [--quick] [-o OUTDIR] [--jobs 2] [--resume]``: the paper's simulation study (alpha selection,
single-frame, dual-frame and accumulated registrations of the six simulated data sets), written as a report
folder (report.md with femreg-vs-paper tables, PNG figures, one record per case).  See :mod:`paperstudy.study`.

:func:`add_parser` is the ``study`` entry of the ``femreg.commands`` entry-point group (pyproject.toml)."""
from __future__ import annotations


def add_parser(subparsers):
    p = subparsers.add_parser(
        "study", help="reproduce the paper's simulation study (report folder with tables and figures)",
        description="Simulate (or load from the cache) the paper's six RF sequences, choose alpha per regulariser "
                    "the paper's way (frames 1 -> 7 of the 3D sequences, log sweep 1e-6 ... 1e6, refined), run "
                    "all four regularisers single-frame, dual-frame and accumulated, and write OUTDIR/report.md "
                    "with every femreg number beside the paper's, plus figures.  Each case is written as it "
                    "finishes; --resume continues an interrupted run.")
    p.add_argument("-o", "--output", default="out/study", metavar="OUTDIR",
                   help="report folder (default out/study, or out/study-quick with --quick)")
    p.add_argument("--quick", action="store_true",
                   help="3D HI only, coarse alpha grid, 7 frames (about 3 min with the data cached)")
    p.add_argument("--jobs", type=int, default=2, help="local worker processes (default 2; 1 = in this process)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the cases on a running Dask scheduler (tcp://host:8786) instead of local processes")
    p.add_argument("--element-size", type=float, metavar="MM",
                   help="registration element size in mm (default: the study's, 2 mm)")
    p.add_argument("--strategy", choices=("paper", "auto"), default=None,
                   help="femreg.register strategy of every case (default: the study's, 'auto'; 'paper' = the "
                        "paper's procedure)")
    p.add_argument("--resume", action="store_true", help="keep finished cases already in OUTDIR")
    p.add_argument("--no-figures", action="store_true", help="tables only")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    import time

    from .study import run_study

    out = args.output
    if args.quick and out == "out/study":
        out = "out/study-quick"
    t0 = time.perf_counter()
    from femreg.errors import InputError
    from .study import StudySettings

    kw = {}
    if args.element_size is not None:
        if not args.element_size > 0:
            raise InputError(f"--element-size must be > 0 mm, got {args.element_size}")
        kw["element_size"] = args.element_size
    if getattr(args, "strategy", None):
        kw["strategy"] = args.strategy
    settings = StudySettings.quick(**kw) if args.quick else StudySettings.full(**kw)
    res = run_study(out, settings=settings, jobs=args.jobs, scheduler=args.scheduler, resume=args.resume,
                    progress=not args.no_progress,
                    figures=not args.no_figures)
    print(f"femreg study ({res.settings.name}): report {res.report} in {time.perf_counter() - t0:.0f} s")
    print("alphas: " + ", ".join(f"{k} {v:.4g}" for k, v in res.alphas.items()))
    row = res.tables.get(("single", "3d-HI"), {}).get("momentum-stress")
    if row:
        print(f"R_P_sigma 3d-HI single frame total strain error {row['e']:.1f}% (paper 10.3%)")
    return 0
