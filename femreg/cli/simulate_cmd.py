"""``femreg simulate``: the paper's six simulated RF sequences (3D x HI/mHI/HOM/SI, plane strain HI, plane stress
HI), generated once and cached on disk (deterministic for a seed); prints each file and its compression schedule
measured from the true strain."""
from __future__ import annotations

import math
import shutil
import time
from pathlib import Path


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


def add_parser(subparsers):
    from forward.sequences import PAPER_DATASETS, dataset_name

    names = ", ".join(dataset_name(m, i) for m, i in PAPER_DATASETS)
    p = subparsers.add_parser(
        "simulate", help="simulate (or load from the cache) the paper's RF image sequences",
        description=__doc__ + f"\n\nData sets: {names}.")
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
    p.set_defaults(func=run)
    return p


def run(args) -> int:
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
