"""Reading users' RF data and writing results.

Readers: :func:`read_frames` (npy, npz, MATLAB v5 / v7.3, MetaImage, raw, Ultrasonix .rf, UFF, HDF5, DICOM
ultrasound images and cine loops, directories of frames) -> :class:`Frames`; :func:`read_volumes` (npy, npz, MATLAB, MetaImage) -> :class:`Volumes`.  Writers: :func:`save_frames` (every reader format), :func:`save_result` /
:func:`load_result` (the result ``.npz`` contract), :func:`write_vtu`, :func:`write_xdmf`, :func:`export_result`
(ParaView); :func:`atomic_savez` / :func:`atomic_write_text` (write to a temporary name, then rename, so a reader
never sees a torn file).  Every failure is a :class:`~femreg.errors.FileFormatError` or :class:`~femreg.errors.InputError`.
"""
from .._atomic import atomic_savez, atomic_write_text
from .frames import Frames, Volumes
from .readers import FORMATS, detect_format, read_frames, read_volumes
from .results import (GRID_FIELDS, RESULT_KEYS, element_strains, export_result, mesh_fields, nodal_average,
                      read_result, save_result, write_vtu, write_xdmf)
from .writers import save_frames, save_volumes

__all__ = ["Frames", "Volumes", "read_frames", "read_volumes", "save_frames", "save_volumes", "detect_format", "FORMATS", "RESULT_KEYS", "GRID_FIELDS",
           "load_result", "read_result", "save_result", "export_result", "write_vtu", "write_xdmf", "element_strains",
           "nodal_average", "mesh_fields", "atomic_savez", "atomic_write_text"]


def __getattr__(name):
    # femreg.io.load_result is femreg.load_result (femreg.result), which writes through femreg.io.results
    if name == "load_result":
        from ..result import load_result

        return load_result
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
