"""Atomic file writes (temporary file in the same folder + rename): an interrupted run never leaves a
half-written result that a resume would trust."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _tmp(path: Path, suffix: str) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")


def atomic_write_text(path, text: str) -> None:
    path = Path(path)
    tmp = _tmp(path, "")
    tmp.write_text(text)
    os.replace(tmp, path)


def atomic_savez(path, writer=None, **arrays) -> None:
    """``np.savez_compressed(path, **arrays)`` atomically; or ``writer(tmp_path)`` writes the .npz itself."""
    path = Path(path)
    tmp = _tmp(path, ".npz")
    if writer is not None:
        writer(tmp)
    else:
        np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
