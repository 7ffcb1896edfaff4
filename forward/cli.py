"""The simulator's ``femreg`` subcommands, contributed through the ``femreg.commands`` entry-point group
(pyproject.toml), so that the registration library never imports the simulator:

* ``femreg simulate``: the paper's six simulated RF sequences, generated once and cached;
* ``femreg forward``: solve a forward (ground-truth) elasticity model and save it.

Each ``add_*_parser(subparsers)`` adds one subcommand and sets ``func`` to its ``run_*(args) -> int``.
"""
from __future__ import annotations

import math
import resource
import shutil
import time
from pathlib import Path

_SIMULATE_DOC = ("Simulate the paper's six RF sequences (3D x HI/mHI/HOM/SI, plane strain HI, plane stress HI), "
                 "generated once and cached on disk (deterministic for a seed); prints each file and its "
                 "compression schedule measured from the true strain.")
_FORWARD_DOC = ("Solve a forward (ground-truth) elasticity model and save it, e.g. "
                "`femreg forward 3d --inclusion-modulus 40 -o out/hi3d.npz` (.vtu also writes a ParaView file). "
                "Prints DOFs, wall time per stage and peak memory.")


def _snr(text: str):
    if text.strip().lower() in ("none", "off"):
        return None
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"--snr-db must be a number of dB or 'none', got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"--snr-db must be finite (or 'none' for no noise), got {text!r}")
    return v


def add_simulate_parser(subparsers):
    from forward.sequences import PAPER_DATASETS, dataset_name

    names = ", ".join(dataset_name(m, i) for m, i in PAPER_DATASETS)
    p = subparsers.add_parser(
        "simulate", help="simulate (or load from the cache) the paper's RF image sequences",
        description=_SIMULATE_DOC + f"\n\nData sets: {names}.")
    p.add_argument("--datasets", default="all",
                   help="comma-separated data set names, or 'all' (default). Names: " + names)
    p.add_argument("--cache-dir", default=None,
                   help="cache directory (default: <femreg cache>/sequences, see FEMREG_CACHE)")
    p.add_argument("--out", default=None, help="also copy each sequence file (.npz) into this directory")
    p.add_argument("--seed", type=int, default=0, help="random seed (scatterers, amplitudes, noise); default 0")
    p.add_argument("--snr-db", type=str, default="12",
                   help="SNR in dB, 10 log10(mean signal power / noise variance); 'none' for no noise; default 12")
    p.add_argument("--n-frames", type=int, default=20, help="frames per sequence (default 20)")
    p.add_argument("--depth-mm", type=float, default=72.0, help="imaged depth from the top face (default 72)")
    p.add_argument("--width-mm", type=float, default=44.0, help="imaged width, centred (default 44)")
    p.add_argument("--refresh", action="store_true", help="re-simulate even if cached")
    p.set_defaults(func=run_simulate)
    return p


def run_simulate(args) -> int:
    from forward.sequences import PAPER_DATASETS, dataset_name, get_sequence, parse_dataset_name, schedule_figures

    if args.datasets.strip().lower() == "all":
        pairs = list(PAPER_DATASETS)
    else:
        pairs = [parse_dataset_name(n.strip()) for n in args.datasets.split(",") if n.strip()]
        if not pairs:
            raise ValueError("--datasets names no data set")
    snr = _snr(args.snr_db)
    if args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    extra = {}
    if args.depth_mm != 72.0:
        extra["depth_mm"] = args.depth_mm
    if args.width_mm != 44.0:
        extra["width_mm"] = args.width_mm
    out = Path(args.out) if args.out else None
    for model, inc in pairs:
        name = dataset_name(model, inc)
        t0 = time.perf_counter()
        seq = get_sequence(model, inc, seed=args.seed, snr_db=snr, n_frames=args.n_frames,
                           cache_dir=args.cache_dir, refresh=args.refresh, **extra)
        dt = time.perf_counter() - t0
        fig = schedule_figures(seq)
        print(f"{name}: {seq.path} ({seq.n_frames} x {seq.shape[0]} x {seq.shape[1]}, "
              f"field {seq.params.get('field_source')}, {dt:.1f} s)")
        line = f"  mean axial compressive strain: total {fig['total']:.3f} %"
        for key, label in (("mean_step", "mean step"), ("max_step", "max step"), ("frames_1_3", "1->3"),
                           ("frames_1_7", "1->7"), ("frames_1_10", "1->10")):
            if key in fig:
                line += f", {label} {fig[key]:.3f} %"
        print(line, flush=True)
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(seq.path, out / f"{name}_seed{args.seed}.npz")
    return 0



def add_forward_parser(subparsers):
    p = subparsers.add_parser("forward", help="solve a forward elasticity model (ground truth) and save it",
                              description=_FORWARD_DOC)
    p.add_argument("model", choices=["plane-strain", "plane-stress", "3d"])
    p.add_argument("-o", "--output", default=None, help="output file (.npz reloadable, .vtu for ParaView); "
                                                         "default forward_<model>.npz")
    p.add_argument("--inclusion-modulus", type=float, default=40.0, help="MPa (default 40, HI)")
    p.add_argument("--background-modulus", type=float, default=10.0, help="MPa (default 10)")
    p.add_argument("--poisson", type=float, default=0.495)
    p.add_argument("--block-mm", type=float, default=160.0)
    p.add_argument("--inclusion-diameter-mm", type=float, default=15.0)
    p.add_argument("--inclusion-depth-mm", type=float, default=30.0)
    p.add_argument("--patch-mm", type=float, default=50.0, help="compression patch width, mm; 0 = whole top face")
    p.add_argument("--compression-mm", type=float, default=1.0)
    p.add_argument("--mesh-size-mm", type=float, default=None, help="element size in the imaged region, mm")
    p.add_argument("--coarse-size-mm", type=float, default=None, help="element size far away, mm")
    p.add_argument("--symmetry", choices=["quarter", "half", "full"], default="quarter", help="3D only")
    p.add_argument("--solver", choices=["auto", "pardiso", "superlu"], default="auto")
    p.add_argument("--cache", action="store_true", help="use the forward-solution disk cache")
    p.set_defaults(func=run_forward)
    return p


def run_forward(args) -> int:
    import forward

    t0 = time.perf_counter()
    sol = forward.solve_elasticity(
        args.model, inclusion_modulus=args.inclusion_modulus, background_modulus=args.background_modulus,
        poisson=args.poisson, block_mm=args.block_mm, inclusion_diameter_mm=args.inclusion_diameter_mm,
        inclusion_depth_mm=args.inclusion_depth_mm, patch_mm=None if args.patch_mm == 0 else args.patch_mm,
        compression_mm=args.compression_mm, mesh_size_mm=args.mesh_size_mm, coarse_size_mm=args.coarse_size_mm,
        symmetry=args.symmetry, solver=args.solver, cache=args.cache)
    out = args.output or f"forward_{args.model}.npz"
    path = sol.save(out)
    i = sol.info
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if "from_cache" in i:
        print(f"loaded from cache {i['from_cache']}")
    print(f"{args.model}: {i['n_dofs']} DOFs ({i['n_elements']} P2 elements), mesh {i['mesh_time_s']:.1f} s, "
          f"assembly {i['assembly_time_s']:.1f} s, solve {i['solve_time_s']:.1f} s ({i['solver']}), "
          f"total {time.perf_counter() - t0:.1f} s, peak memory {peak:.0f} MB, "
          f"reaction force {i['reaction_force']:.3f} {'N' if args.model == '3d' else 'N/mm'}")
    print(f"saved {path}")
    return 0
