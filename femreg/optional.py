"""Optional dependencies: import them where they are used, with an error that names the pip extra.

``pip install femreg`` installs the core (registration, tracking, inversion, readers, matplotlib pictures);
the extras of pyproject.toml add the rest::

    pip install "femreg[fast]"     # numba: compiled inner loops, ~5x faster Gauss-Newton iterations
    pip install "femreg[batch]"    # dask.distributed: femreg batch, the paper's study
    pip install "femreg[vtk]"      # meshio + pyvista: ParaView files (VTU/XDMF), mesh files, 3D renderings
    pip install "femreg[amg]"      # pyamg: the algebraic-multigrid linear solver option
    pip install "femreg[forward]"  # gmsh, meshio, pypardiso: the forward FE models and the RF simulator
    pip install "femreg[dicom]"    # pydicom: clinical DICOM ultrasound images and cine loops (femreg.io.dicom)
    pip install "femreg[all]"      # all of the above
"""
from __future__ import annotations

import importlib

__all__ = ["MissingDependencyError", "EXTRAS", "require"]

#: Import name -> (distribution name on PyPI, extra of femreg that installs it).
EXTRAS = {
    "numba": ("numba", "fast"),
    "dask": ("dask", "batch"),
    "distributed": ("distributed", "batch"),
    "meshio": ("meshio", "vtk"),
    "pyvista": ("pyvista", "vtk"),
    "pyamg": ("pyamg", "amg"),
    "gmsh": ("gmsh", "forward"),
    "pypardiso": ("pypardiso", "forward"),
    "pydicom": ("pydicom", "dicom"),
}


class MissingDependencyError(ImportError):
    """An optional package is not installed; the message names the femreg extra that installs it."""


def require(module: str, extra: str | None = None, *, feature: str | None = None):
    """Import and return ``module``; raise :class:`MissingDependencyError` naming the extra when it is absent.

    Parameters
    ----------
    module : str
        Import name, e.g. ``"pyvista"`` or ``"distributed"``.
    extra : str, optional
        The femreg extra that installs it (default: looked up in :data:`EXTRAS`).
    feature : str, optional
        What needs it, for the message (e.g. ``"femreg batch"``).

    Returns
    -------
    module
        The imported module.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        top = module.split(".")[0]
        dist, default_extra = EXTRAS.get(top, (top, None))
        extra = extra or default_extra
        what = feature or "this femreg function"
        hint = f"pip install 'femreg[{extra}]'" if extra else f"pip install {dist}"
        raise MissingDependencyError(f"{what}: the optional package {dist!r} is not installed ({exc}); "
                                     f"install it with: {hint}") from exc
