"""``femreg info FILE``: what is in an RF data file (format, frames, shape, dtype, spacing, values, header)."""
from __future__ import annotations

import json

import numpy as np

from ._common import add_reader_args, frames_from_args


def add_parser(subparsers):
    p = subparsers.add_parser(
        "info", help="describe an RF data file (format, frames, shape, spacing, header)",
        description="Read FILE (npy, npz, mat v5/v7.3, mhd/mha, raw, Ultrasonix .rf, or a directory of "
                    "per-frame files) and print its format, number of frames, frame shape (axial x lateral), "
                    "sample type, spacing, value range and header fields.  Exit 2 with a one-line reason if "
                    "the file cannot be read.")
    p.add_argument("file", help="data file or directory of frame files")
    add_reader_args(p)
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    p.set_defaults(func=run)
    return p


def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v if isinstance(v, (int, float, str, bool, type(None))) else str(v)


def describe(fr) -> dict:
    a = fr.frames
    meta = dict(fr.metadata)
    return {
        "file": str(fr.source), "format": meta.pop("format", ""), "frames": fr.n_frames,
        "shape": list(fr.shape), "dtype": str(a.dtype), "spacing_mm": list(fr.spacing),
        "origin_mm": list(fr.origin),
        "extent_mm": [fr.shape[0] * fr.spacing[0], fr.shape[1] * fr.spacing[1]],
        "min": float(a.min()), "max": float(a.max()), "mean": float(a.mean()), "std": float(a.std()),
        "metadata": _plain(meta),
    }


def run(args) -> int:
    info = describe(frames_from_args(args, allow_sector=True))
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"file      {info['file']}")
    print(f"format    {info['format']}")
    print(f"frames    {info['frames']}")
    print(f"shape     {info['shape'][0]} axial x {info['shape'][1]} lateral")
    print(f"dtype     {info['dtype']}")
    print(f"spacing   {info['spacing_mm'][0]:g} mm axial, {info['spacing_mm'][1]:g} mm lateral")
    print(f"origin    {info['origin_mm'][0]:g}, {info['origin_mm'][1]:g} mm")
    print(f"extent    {info['extent_mm'][0]:g} mm x {info['extent_mm'][1]:g} mm")
    print(f"values    min {info['min']:.6g}, max {info['max']:.6g}, mean {info['mean']:.6g}, "
          f"std {info['std']:.6g}")
    for key, val in info["metadata"].items():
        if isinstance(val, dict):
            print(f"{key}:")
            for k, v in val.items():
                print(f"  {k:24s} {v}")
        elif isinstance(val, list) and len(val) > 12:
            print(f"{key:9s} {val[:6]} ... ({len(val)} items)")
        else:
            print(f"{key:9s} {val}")
    return 0
