"""``femreg.register``: two-frame FE image registration (eq:objf = eq:IR + R).

Convention: ``reference(x) ~ moving(x + u(x))``; images are (axial, lateral) = (x, y) arrays, pixel [i, j] centre
at ``origin + (i dx, j dy)`` mm.  With ``offset=S`` the problem is eq:IR of a sequence:
``I_k(x + S(x)) ~ I_{k+1}(x + S(x) + u(x))`` (reference = I_k, moving = I_{k+1}).

:func:`register` runs named stages passing plain data: validate the inputs -> normalise each frame (minus its
mean, over its spread) and build the spline coefficients once (:mod:`femreg.image`) -> mesh (ROI sized from the
speckle, or the user's; :mod:`femreg.mesh`) -> initial guess (:mod:`femreg.initial`: coarse-to-fine pyramid, :mod:`femreg.pyramid`, or
the paper's NCC block matching and coarse pass, :mod:`femreg.paperguess`; the pyramid's search first, whose block
matching decides a cut of noise at depth before any solve: :func:`noise_at_depth` runs register up to that
decision) -> Gauss-Newton on the final mesh
(:mod:`femreg.gnsolve`: SSD term with the fixed reference gradient, eq:wfnew, + a fresh regulariser weighted per
2 x 2 mm element, :mod:`femreg.scaling`) -> repair and check (:mod:`femreg.repair`: peak hopping, failure rules,
never worse than the start) -> :class:`femreg.result.RegistrationResult`.  The strategies' settings live in
:mod:`femreg.strategy`; ``alpha="auto"`` in :mod:`femreg.autoalpha`.
"""
from __future__ import annotations

import contextlib
import contextvars
import copy
import dataclasses
import functools
import inspect
import time

import numpy as np

from . import autoalpha, orientation
from .echo import DataMask, as_data_mask, crop_for, noise_share, registering_crop, unmatched_crop
from .errors import InputError
from .gnsolve import image_term, solve  # noqa: F401  (image_term: also femreg.registration.image_term)
from .image import SplineImage, depth_fall_note, ncc, normalize_pair  # noqa: F401  (ncc: also femreg.registration.ncc)
from .image import validate_image, validate_spacing
from .initial import INITIAL_NAMES, Previous, initial_guess, previous_or_fresh, start_search
from .mesh import as_quad_mesh, check_element_size, check_mesh_in_image, roi_mesh
from .paperguess import COARSE_TO_FINE_STRAIN  # noqa: F401
from .pixels import PointLocator
from .refine import (DEFAULT as DEFAULT_REFINE, as_refinement, default_refine, parent_cells, refine_stage,
                     with_refinement)
from .pyramid import image_settings
from .speckle import rf_period
from .regularizers import Regularizer, available_regularizers
from .repair import ENVELOPE_NOTE, check_period, check_result, repair_peak_hopping
from .result import RegistrationResult, displacement_at, load_result, nodal_values  # noqa: F401
from .solver import GN_STRAIN_TOL, GN_STRAIN_TOL_TIGHT, single_blas_thread
from .volume import volumes_to
from .strategy import (DEFAULT_HOURGLASS, DEFAULT_MOMENTUM_STRESS_OPTIONS, STRATEGIES,  # noqa: F401
                       component_tol, effective_regularizer_options, fresh_regularizer, lambda_bar_follows_data,
                       lambda_bar_stage)

__all__ = ["register", "load_result", "ncc", "nodal_values", "displacement_at",
           "COARSE_TO_FINE_STRAIN", "STRATEGIES"]


def _validate(reference_image, moving_image, spacing, origin, *, regularizer, strategy, initial, maxiter, tol,
              strain_tol, check_orientation=True, refine=None):
    """Validate stage: the two images (float64, same shape), spacing and origin (mm), and every option;
    :class:`~femreg.errors.InputError` naming the bad one (a reference frame that looks transposed:
    :class:`femreg.orientation.OrientationError`, unless ``check_orientation`` is False).  Returns ``(ref, mov, spacing, origin, initial)`` with
    ``initial`` None replaced by the strategy's own start."""
    ref = validate_image(reference_image, "reference image")
    mov = validate_image(moving_image, "moving image")
    if ref.shape != mov.shape:
        raise InputError(f"image shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    one_value = np.ndim(spacing) == 0
    spacing, origin = validate_spacing(spacing, origin)
    if check_orientation:
        orientation.check(ref, spacing, one_value=one_value)
    if strategy not in STRATEGIES:
        raise InputError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    if not isinstance(regularizer, (str, Regularizer)):
        raise InputError(f"regularizer must be a name or a Regularizer, got {type(regularizer).__name__}")
    if isinstance(regularizer, str) and regularizer not in available_regularizers():
        raise InputError(f"unknown regularizer {regularizer!r}; choose one of {available_regularizers()}")
    if int(maxiter) < 0 or not (np.isfinite(tol) and tol > 0):
        raise InputError(f"need maxiter >= 0 and tol > 0, got maxiter={maxiter}, tol={tol}")
    if strain_tol is not None and not (isinstance(strain_tol, (int, float)) and np.isfinite(strain_tol)
                                       and strain_tol >= 0):
        raise InputError(f"strain_tol must be a finite number >= 0 or None, got {strain_tol!r}")
    as_refinement(refine)
    if initial is None:
        initial = "pyramid" if strategy == "auto" else "blockmatch"
    if isinstance(initial, Previous) and initial.fresh is None:
        initial = Previous(initial.u, "pyramid" if strategy == "auto" else "blockmatch")
    if isinstance(initial, str) and initial not in INITIAL_NAMES:
        raise InputError(f"initial must be 'pyramid', 'blockmatch', 'zero', a callable or a nodal vector, "
                         f"got {initial!r}")
    return ref, mov, spacing, origin, initial


def _refuse_the_same_frame(ref, mov, initial, offset) -> None:
    """InputError for two images of the same samples from the strategy's own start, as :func:`femreg.track`
    refuses a repeated frame: Gauss-Newton's relative step never falls below ``tol`` at u = 0 (in vivo: 20
    iterations and rows refined on a zero field).  A given start or offset is a caller's test of the solver."""
    if offset is None and isinstance(initial, str) and np.array_equal(ref, mov):
        raise InputError("the reference and moving images hold the same samples: nothing moved, nothing to "
                         "register (the same frame twice, e.g. frames[0] and frames[0]?)")


def _chosen_start(initial, ref, mov, I1, I2, mesh, spacing, origin, offset, locator):
    """``(initial, note, term)`` of :func:`femreg.initial.previous_or_fresh`: a track's previous increment
    (:class:`femreg.initial.Previous`) unless the frames match better without it, the image term on ``mesh``
    built to decide; then the refusal of the same frame twice from the strategy's own start."""
    initial, note, term = previous_or_fresh(initial, lambda: image_term(I1, I2, mesh, ref.shape, spacing, origin,
                                                                        offset=offset, locator=locator), mesh)
    _refuse_the_same_frame(ref, mov, initial, offset)
    return initial, note, term


def _mesh_stage(ref, spacing, origin, *, mesh, element_size, margin, strategy, initial, regularizer,
                allow_mesh_outside, rectangle=None):
    """Mesh stage: the user's mesh, or the structured ROI mesh sized from the speckle (``strategy="auto"``, whose
    speckle statistics and pyramid settings are returned for the pyramid) or from ``element_size``.  Returns
    ``(mesh, stats, settings)``; ``rectangle`` (slices): the statistics from this part of ``ref`` only (a fan's
    largest rectangle without fill)."""
    check_element_size(element_size, spacing, mesh)
    stats = settings = None
    need_stats = mesh is None or (isinstance(initial, str) and initial == "pyramid")
    if strategy == "auto" and need_stats:
        part = ref if rectangle is None else ref[rectangle]
        stats, settings = image_settings(part, spacing, element_size, regularizer)
    if mesh is None:
        h = settings.element_size if (settings is not None and element_size is None) else element_size
        fe_mesh = roi_mesh(ref.shape, spacing, origin, element_size=None if h is None else tuple(np.ravel(h)),
                           margin=margin)
    else:
        fe_mesh = as_quad_mesh(mesh)
    if not allow_mesh_outside:
        check_mesh_in_image(fe_mesh, ref.shape, spacing, origin)
    return fe_mesh, stats, settings


def _image_stage(ref, mov, spacing, origin, normalize, data_mask=None):
    """Images stage: each frame normalised by its mean and spread (over the fan of a scan-converted frame, the
    ``data_mask`` of :func:`register` as :func:`femreg.echo.as_data_mask` reads it), spline coefficients once;
    eq:IR weight 0 outside the fan's ``weights``.  Returns ``(ref, mov, I1, I2, fan)``, ``fan`` the
    :class:`femreg.echo.DataMask` (its ``rectangle`` the largest rectangle without fill) or None."""
    fan = as_data_mask(data_mask, ref.shape, spacing)
    if normalize:
        ref, mov, _ = normalize_pair(ref, mov, mask=None if fan is None else fan.inside)
    I1, I2 = SplineImage(ref, spacing, origin), SplineImage(mov, spacing, origin)
    if fan is not None:
        I1.weights_mask = fan.weights   # read by femreg.gnsolve.image_term
    return ref, mov, I1, I2, fan


def _masked(res, fan, data_mask):
    """``res`` NaN outside a user's ``data_mask`` on frames not cut to it (``fan`` its DataMask); a DataMask handed
    down from a crop is the crop's to apply (:meth:`femreg.echo.Crop.widen`)."""
    if fan is not None and not isinstance(data_mask, DataMask):
        res.data_mask = fan.inside.copy()
    return res


def _registered_crop(crop, args: dict):
    """:func:`register` (keyword arguments ``args``) on the frames cut to ``crop`` (:class:`femreg.echo.Crop`), the
    result on the full frames' pixel grid; a fan's fill weighted 0 in eq:IR and the result NaN outside it
    (:func:`femreg.echo.fan_region`); the noise floor left out known to the refinement (:func:`femreg.echo.noise_share`)."""
    frames = crop.frames(args["reference_image"], args["moving_image"])
    kw = {k: v for k, v in args.items() if k not in ("reference_image", "moving_image")}
    kw.update(roi=None, depth=None, origin=crop.origin, data_mask=crop.mask)
    with registering_crop(noise_share(crop.region, frames[0])):
        return crop.widen(register(*frames, **kw))


def _cuts_at_depth(args: dict) -> bool:
    """Whether :func:`register` (keyword arguments ``args``) looks for noise at depth after its start: only where
    it detects the echo itself (``roi="auto"``, nothing given that fixes the region)."""
    return (isinstance(args["roi"], str) and args["depth"] is None and args["mesh"] is None
            and args["initial"] is None and args["offset"] is None and args["data_mask"] is None)


#: Set while :func:`noise_at_depth` runs :func:`register` for its cut alone (:class:`_CutDecided`).
_DECIDING = contextvars.ContextVar("femreg_registration_deciding", default=False)


class _CutDecided(Exception):
    """Raised by :func:`register`'s noise-at-depth decision in :func:`noise_at_depth`'s context: the decision
    (``crop``, a :class:`femreg.echo.Crop` or None) is all it asked for, no solve follows."""

    def __init__(self, crop):
        super().__init__("noise at depth decided")
        self.crop = crop


def _noise_at_depth(found, args: dict, shape, spacing, origin):
    """The crop above rows at the bottom that the block matching of the default start found no match in
    (:func:`femreg.echo.unmatched_crop`: noise a time-gain compensation lifts to the echo's level), or None; only
    where :func:`register` detects the echo itself (:func:`_cuts_at_depth`).  ``found``: the start's first part
    that holds its block matching (:func:`femreg.initial.start_search`'s pyramid search, or the paper's
    :class:`femreg.initial.InitialGuess`), or None; ``spacing``, ``origin``: validated.  Under
    :func:`noise_at_depth` the decision ends the registration (:class:`_CutDecided`)."""
    if found is None:
        return None
    crop = unmatched_crop(found.blockmatch, shape, spacing, origin, margin=args["margin"]) if _cuts_at_depth(
        args) else None
    if _DECIDING.get():
        raise _CutDecided(crop)
    return crop


#: While a loop shares its first pair's start (:func:`sharing_start`): a dict that :func:`noise_at_depth` leaves
#: the search it made in (``"search"``: :class:`_Handed`), for the loop's own registration of that pair.
_SHARED = contextvars.ContextVar("femreg_registration_shared_start", default=None)


@dataclasses.dataclass
class _Handed:
    """A start's search (:class:`femreg.pyramid.PyramidSearch`) with what it was computed from: the normalised
    frames, their grid, the speckle statistics and settings (:func:`_search_stage`)."""

    ref: np.ndarray
    mov: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    search: object

    def fits(self, ref, mov, spacing, origin, stats, settings) -> bool:
        """Whether a search on these (normalised frames, grid, statistics, settings) is this one."""
        same = [(self.spacing, spacing), (self.origin, origin), (self.ref, ref), (self.mov, mov)]
        for a, b in ((self.search.stats, stats), (self.search.settings, settings)):
            same += [(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a) if f.compare]
        return all(np.shape(x) == np.shape(y) and np.array_equal(x, y) for x, y in same)


@contextlib.contextmanager
def sharing_start(handed=None):
    """Context in which :func:`noise_at_depth` hands the start it computed for its decision (the pyramid's search)
    to a later :func:`register` of the same frames with the same statistics and settings, which takes it instead of
    searching again (bit-identical: the search depends on nothing else).  :func:`femreg.track` and
    :func:`femreg.elastogram` decide their cut on the first pair that differs and then register it.  ``handed``:
    a search :func:`shared_search` took from such a context in another process or thread (an elastogram's Dask
    workers, which do not see this one's context), offered there in the same way."""
    token = _SHARED.set({} if handed is None else {"search": handed})
    try:
        yield
    finally:
        _SHARED.reset(token)


def shared_search():
    """The search :func:`noise_at_depth` left in the current :func:`sharing_start` context (picklable), or None:
    for :func:`sharing_start` (``handed``) where the pair is registered."""
    box = _SHARED.get()
    return None if box is None else box.get("search")


def _search_stage(initial, ref, mov, I1, I2, fe_mesh, spacing, origin, *, regularizer, offset, stats, settings,
                  element_size, rectangle):
    """:func:`femreg.initial.start_search` (arguments as there), or the search :func:`noise_at_depth` made on these
    very frames and settings (:func:`sharing_start`); a search made under :func:`noise_at_depth` is left for it."""
    box = _SHARED.get()
    plain = box is not None and offset is None and rectangle is None and stats is not None
    handed = box.get("search") if plain else None
    if handed is not None and isinstance(initial, str) and initial == "pyramid" and handed.fits(
            ref, mov, spacing, origin, stats, settings):
        return handed.search
    search = start_search(initial, ref, mov, I1, I2, fe_mesh, spacing, origin, regularizer=regularizer, offset=offset,
                          stats=stats, settings=settings, element_size=element_size, rectangle=rectangle)
    if plain and search is not None and _DECIDING.get():
        box["search"] = _Handed(ref, mov, np.asarray(spacing, float), np.asarray(origin, float), search)
    return search


def noise_at_depth(reference_image, moving_image, *, spacing, origin=(0.0, 0.0), **register_kwargs):
    """The crop :func:`register` would cut the pair to after its default start for noise at depth (a time-gain
    compensation lifting the receiver noise to the echo's level: :func:`femreg.echo.unmatched_crop`), or None.

    For :func:`femreg.track` and :func:`femreg.elastogram`, which choose one crop for a whole loop from one pair
    and register every pair on one mesh: called where :func:`femreg.echo.crop_for` found nothing to cut by level
    (register's own order).  ``reference_image``, ``moving_image``: (n_axial, n_lateral) frames; ``spacing``,
    ``origin`` mm; ``register_kwargs``: :func:`register`'s keyword arguments (``roi``, ``depth``, ``mesh``,
    ``data_mask``, ``initial``, ``offset`` decide whether it looks at all, as in register; ``strategy``,
    ``regularizer``, ``element_size``, ``margin``, ``blockmatch_options``, ... make the start).  :func:`register`
    itself runs, up to its decision: validate, images, mesh and the start's block matching (the pyramid's search
    with ``strategy="auto"``, before any solve; the paper's start with no Gauss-Newton after it); none of its
    hand-offs (probe geometry, echo crop, ``alpha="auto"``: the caller has made those choices).  The returned
    :class:`femreg.echo.Crop` is on these frames."""
    args = {k: p.default for k, p in inspect.signature(register).parameters.items()
            if p.default is not inspect.Parameter.empty}
    unknown = set(register_kwargs) - set(args)
    if unknown:
        raise InputError(f"unknown keyword arguments of register: {sorted(unknown)}")
    args.update(register_kwargs)
    if not _cuts_at_depth(args) or args["geometry"] is not None:
        return None
    # "auto": the start needs no alpha chosen; maxiter 0: no Gauss-Newton in the paper's start
    kw = dict(register_kwargs, alpha=None if isinstance(args["alpha"], str) else args["alpha"], maxiter=0,
              check_orientation=False)
    token = _DECIDING.set(True)
    try:
        register(reference_image, moving_image, spacing=spacing, origin=origin, **kw)
    except _CutDecided as decided:
        return decided.crop
    finally:
        _DECIDING.reset(token)
    raise RuntimeError("register returned without deciding its noise-at-depth cut")


def _route(reference_image, moving_image, args: dict):
    """The calls :func:`register` hands on before its own stages, each calling :func:`register` back: convex /
    sector frames (:func:`femreg.geometry.register_beam`), the echo rectangle (:func:`femreg.echo.crop_for`) and
    ``alpha="auto"`` (:func:`femreg.autoalpha.register_auto`).  ``args``: register's keyword arguments.  Returns
    the result, or None when the pair is registered as given (always under :func:`noise_at_depth`, whose caller
    made those choices)."""
    if _DECIDING.get():
        return None
    geometry = args["geometry"]
    if geometry is not None:            # convex / sector frames: femreg.geometry (calls back for sample space)
        from .geometry import as_geometry, register_beam
        if as_geometry(geometry) is not None:
            if args["data_mask"] is not None:
                raise InputError("data_mask is on a Cartesian pixel grid: not with a convex / sector geometry")
            kw = {k: v for k, v in args.items() if k not in ("reference_image", "moving_image", "geometry")}
            return register_beam(reference_image, moving_image, geometry=geometry, register=register, **kw)
    # a DataMask describes these very frames (the fan handed down from a crop): nothing more to crop
    try:
        crop = None if isinstance(args["data_mask"], DataMask) else crop_for(
            reference_image, moving_image, args["spacing"], args["origin"], roi=args["roi"], depth=args["depth"],
            mesh=args["mesh"], margin=args["margin"], initial=args["initial"], offset=args["offset"], fan=True,
            data_mask=args["data_mask"])
    except InputError:
        # frames read with their spacings exchanged (or transposed) leave the echo search a sliver of the frame:
        # the orientation check on the whole frame names the cause, where the crop's refusal names the sliver
        if args["check_orientation"]:
            orientation.check(validate_image(reference_image, "reference image"),
                              validate_spacing(args["spacing"], args["origin"])[0],
                              one_value=np.ndim(args["spacing"]) == 0)
        raise
    kw = {k: v for k, v in args.items() if k not in ("reference_image", "moving_image")}
    kw.update(roi=None, depth=None)
    if crop is not None:                # inside the echo rectangle, on the full frames' grid (femreg.echo)
        return _registered_crop(crop, args)
    if isinstance(args["alpha"], str):  # alpha="auto": chosen from the pair alone (femreg.autoalpha)
        if args["check_orientation"]:   # once here, not in each candidate registration
            orientation.check(validate_image(reference_image, "reference image"),
                              validate_spacing(args["spacing"], args["origin"])[0])
        return autoalpha.register_auto(reference_image, moving_image, register=register,
                                       **dict(kw, check_orientation=False))
    return None


@volumes_to          # RF volumes (3D arrays) go to femreg.volume.register_volume
@single_blas_thread
def register(reference_image, moving_image, *, spacing, origin=(0.0, 0.0), regularizer="momentum-stress",
             alpha=None, mesh=None, element_size=None, margin=None, initial=None, offset=None,
             maxiter: int = 20, tol: float = 1e-3, linear_solver: str = "auto", blockmatch_options=None,
             regularizer_options=None, normalize: bool = True, callback=None, allow_mesh_outside: bool = False,
             coarse_to_fine="auto", strategy: str = "auto", repair: bool = True,
             strain_tol: float | None = None, roi="auto", depth=None,
             check_orientation: bool = True, geometry=None, refine=DEFAULT_REFINE,
             data_mask=None) -> RegistrationResult:
    """Register ``moving_image`` to ``reference_image``: find u minimising eq:objf = psi (eq:IR) + R[u].

    Stages (each passes plain data to the next): validate -> images -> mesh -> initial guess
    (:mod:`femreg.initial`) -> solve (:mod:`femreg.gnsolve`) -> repair and check (:mod:`femreg.repair`) ->
    :class:`RegistrationResult`.

    Parameters
    ----------
    reference_image, moving_image : (n_axial, n_lateral) real array
        I_1 and I_2 (RF or any intensity), same shape.  Convention: reference(x) ~ moving(x + u(x)).
    spacing : (dx, dy) mm
        Pixel spacing (axial, lateral); a scalar means square pixels (RF frames whose lateral speckle is then
        narrower than two axial RF periods are refused: :func:`femreg.orientation.check`, ``one_value``).
    origin : (2,) mm
        Centre of pixel [0, 0].
    regularizer : str or Regularizer
        A name from :func:`femreg.regularizers.available_regularizers`: "momentum-stress" = R_P_sigma (default),
        "momentum-strain" = R_P_eps, "strain" = R_eps, "strain-incompressible" = R_eps_i; or a Regularizer
        instance (copied, never changed).
    alpha : float or "auto", optional
        :math:`\\alpha` of eq:objf for normalised images (:func:`femreg.image.normalize_pair`) and 2 x 2 mm
        elements; on other meshes the weight is scaled by 4 mm^2 / mean element area (:mod:`femreg.scaling`).
        None = the regulariser's default (femreg/data/default_alphas.json, selected by the paper's procedure); "auto" = chosen from the pair
        without ground truth by :func:`femreg.autoalpha.choose_alpha` (several registrations).
    mesh : skfem.MeshQuad1, meshio.Mesh or path, optional
        A user's quad mesh (mm, [x, y]); default: structured ROI mesh (:func:`femreg.mesh.roi_mesh`).
    element_size, margin : float or (2,) mm, optional
        For the default ROI mesh.  ``element_size`` None: from the speckle size (``strategy="auto"``,
        :func:`femreg.pyramid.default_settings`) or :data:`femreg.mesh.DEFAULT_ELEMENT_SIZE` (``"paper"``).
    initial : None, "pyramid", "blockmatch", "zero", callable, (2 n_nodes,) array, RegistrationResult or BlockMatchResult
        Initial guess u_1.  None: the strategy's own ("pyramid" for "auto", "blockmatch" for "paper").
        "pyramid": coarse-to-fine envelope search and envelope-level Gauss-Newton (:mod:`femreg.pyramid`);
        "blockmatch": NCC block matching with ``blockmatch_options`` (paper: 5 x 9 mm windows).
    offset : callable | (2 n_nodes,) array | RegistrationResult, optional
        S of eq:IR: both images are sampled at x + S(x) (sequence tracking); None = 0.
    maxiter, tol
        Gauss-Newton stopping rule: ``maxiter`` iterations or ``||du|| / ||u|| < tol`` (paper 20, 1e-3); with
        ``strategy="auto"`` the final solve scales ``tol`` to the smaller displacement component
        (:func:`femreg.strategy.component_tol`).
    linear_solver : {"auto", "cholesky", "splu", "spsolve", "amg-cg"} (see :mod:`femreg.solver`)
    blockmatch_options : dict, optional
        Keyword arguments of :func:`femreg.blockmatch.block_match` for ``initial="blockmatch"``.
    regularizer_options : dict, optional
        Extra keyword arguments of the regulariser factory.  With ``strategy="auto"`` the momentum regularisers
        get ``hourglass=``:data:`femreg.strategy.DEFAULT_HOURGLASS`, R_P_sigma ``dilatation="centre"`` and
        ``hourglass=1000``
        (:data:`femreg.strategy.DEFAULT_MOMENTUM_STRESS_OPTIONS`) unless given here; and R_P_sigma's
        ``lambda_bar`` (eq:meq) follows the data's lateral-to-axial strain ratio (plane stress's 2 or plane
        strain's 9: the solve is repeated with 9 where the data read plane strain,
        :func:`femreg.strategy.data_lambda_bar`; said in the message) unless ``lambda_bar`` is given here.
    normalize : bool
        Subtract each image's mean and divide it by its spread (default; makes alpha scale- and offset-free:
        :func:`femreg.image.normalize_pair`).
    callback : callable(u, info), optional
        Called after each Gauss-Newton iteration of the final solve and of each refinement pass (``u`` then on
        the refined mesh, ``info["nit"]`` counted per solve).
    coarse_to_fine : "auto" | bool
        ``strategy="paper"`` only: register first on a 3x coarser mesh from the block-matching start when its
        global strain exceeds :data:`femreg.paperguess.COARSE_TO_FINE_STRAIN` (3D SI frames 1 -> 10: total strain
        error 349 % -> 11 %); True always, False never.
    allow_mesh_outside : bool
        Accept a mesh whose nodes partly leave the image (elements there are held by the regulariser alone);
        :func:`femreg.track` uses it for meshes moved with the tissue.  At least one pixel must lie inside.
    strategy : {"auto", "paper"}
        "auto" (default): defaults from the image, pyramid start, peak-hopping repair.  "paper": the paper's
        procedure (fixed 5 x 9 mm block matching, 2 mm mesh, companding and the coarse pass at large strain).
        Both end with the check stage (never worse than the start, success=False with a message on failure).
    repair : bool
        Detect and repair peak hopping (default True).
    strain_tol : float, optional
        ``strategy="auto"``: the final solve also stops once a step changes the element strains by less than this
        fraction of their RMS (on two consecutive steps); None = :data:`femreg.solver.GN_STRAIN_TOL` (1.5 %, the
        TV regularisers) or :data:`femreg.solver.GN_STRAIN_TOL_TIGHT` (0.5 %, the quadratic ones), 0 = only
        the ``tol`` rule.
    roi : "auto" | None | (x0, x1, y0, y1) mm, for volumes (x0, x1, y0, y1, z0, z1) mm
        The region registered (volumes: :func:`femreg.echo_volume.find_echo_volume`, the full voxel grid kept).
        "auto" (default): the rectangle with usable echo (:func:`femreg.echo.find_echo`: depth and lines at the
        noise floor, saturated samples), the rest left out of the mesh and the image term and named in
        ``result.excluded`` and the message (nothing changes where the frames hold echo everywhere); envelope /
        B-mode frames with fill around a scan-converted fan (:func:`femreg.echo.find_fill`): the whole fan, the
        fill weighted 0 in eq:IR and the result NaN outside the fan (:func:`femreg.echo.fan_region`); None: the
        whole frames; a rectangle: that one (no detection).  The mesh covers the rectangle, less ``margin`` at
        the image edges; the result keeps the full frames' pixel grid.
    depth : (d0, d1) mm, optional
        A given depth range over all lines (instead of ``roi``; no detection).  Either outside the image is an
        :class:`~femreg.errors.InputError` naming the image extent.  With a user ``mesh`` neither applies.
    check_orientation : bool
        Refuse a reference frame that looks transposed or whose spacing looks swapped or implausible, from its RF
        carrier (:mod:`femreg.orientation`; :class:`femreg.orientation.OrientationError`); data without a
        carrier (envelope, B-mode) is never refused.  False skips the check.
    geometry : femreg.Convex | femreg.Sector, optional
        Frames sampled along the rays of a convex or phased array, (n_samples, n_rays) with ``spacing`` = dr mm
        (or (dr mm, dtheta deg)) and ``origin`` = (range of the first sample mm, 0); registered, and returned as
        a :class:`femreg.geometry.BeamResult`, in physical Cartesian coordinates (conventions:
        :mod:`femreg.geometry`).  None: a linear array (the pixel grid above).  Volumes take a
        :class:`femreg.Swept` (a swept probe's fan of frames, :mod:`femreg.swept`).
    refine : "default" | None | int | "auto" | "slip" | "none" | femreg.refine.Refinement
        Adaptive refinement after the solve (:mod:`femreg.refine`): mark the elements where the data ask for more
        resolution (jumps of A[u] across edges by default), split their rows / columns of the tensor mesh and solve
        again from the solution, one Gauss-Newton step each: ``N`` passes of :class:`femreg.refine.Refinement`
        (each halving the marked rows / columns), "auto": :data:`femreg.refine.DEEP_REFINEMENT` (one pass
        quartering them, with the local relaxation of layers across the image, and a lower marking cut with
        columns down to 0.4 mm where a feature stands out far); "slip": :data:`femreg.refine.SLIP_REFINEMENT`
        (shear bands: the band's rows thinned and its shear traction let through); the weight of eq:objf stays
        the unrefined mesh's.  Names in any case, as the CLI's ``--refine``.
        "default": "auto" for ``strategy="auto"`` with R_P_sigma (the default regulariser) on the default ROI mesh, off for ``strategy="paper"``, the other regularisers, a user's mesh
        or ``element_size`` (so every increment of
        :func:`femreg.track`), an offset, a convex / sector geometry (where ``"auto"`` / N refines the (range,
        angle) lattice: opt-in, docs/geometry.md) and ``alpha="auto"`` (:func:`femreg.refine.default_refine`);
        volumes follow the same rule with their own refinement (:mod:`femreg.volume_refine`; off for
        :func:`femreg.track` and swept volumes).  None, 0, "none" or "off": off.  The result's mesh, ``u`` and ``quality`` are those of the final
        mesh.
    data_mask : None | (n_axial, n_lateral) bool array | femreg.echo.DataMask
        Where the frames hold data (True), e.g. the fan of a scan-converted convex / phased frame.  None
        (default): found from the frames with ``roi="auto"`` (:func:`femreg.echo.find_fill`, above).  An array:
        that fan instead of any detection: the frames are cut to its bounding box (with ``roi=None``, a user
        ``mesh`` or a nodal ``initial`` / ``offset``: not cut), normalised over it, eq:IR weighted 0 outside it
        and within the fan's border band (:func:`femreg.echo.fan_weights`), the pyramid started on its largest
        rectangle, and the result NaN outside it (``result.data_mask``); True everywhere is the same as
        ``roi=None``.  Not with a given ``roi`` / ``depth`` or a ``geometry``; volumes take none.  A
        :class:`femreg.echo.DataMask` is the form passed on to the registration of the cut frames (no crop).

    Returns
    -------
    RegistrationResult
        ``success`` is False, with a message, when the result explains less of the image than its start (the
        start is returned then), when the images do not match (NCC after below :data:`femreg.repair.MIN_NCC`, or
        more than :data:`femreg.repair.MAX_POOR_FRACTION` of the elements below it), when peak hopping could not
        be repaired, or when more than :data:`femreg.repair.MAX_HOPPED_FRACTION` of the elements match the envelope
        better one RF period off (:func:`femreg.repair.hop_gain`; every strategy); ``quality`` holds the
        per-element NCC, ``hop_gain`` the peak-hopping map.
    """
    refine = default_refine(refine, strategy=strategy, regularizer=regularizer, mesh=mesh, element_size=element_size,
                            offset=offset, geometry=geometry, alpha=alpha, allow_mesh_outside=allow_mesh_outside)
    routed = _route(reference_image, moving_image, args := dict(locals()))
    if routed is not None:              # probe geometry, echo crop or alpha="auto": register is called back
        return routed
    t_all, timings = time.perf_counter(), {}
    ref, mov, spacing, origin, initial = _validate(
        reference_image, moving_image, spacing, origin, regularizer=regularizer, strategy=strategy, initial=initial,
        maxiter=maxiter, tol=tol, strain_tol=strain_tol, check_orientation=check_orientation, refine=refine)
    user_reg = fresh_regularizer(regularizer, alpha, effective_regularizer_options(strategy, regularizer,
                                                                                   regularizer_options))
    reg_factory = functools.partial(copy.copy, user_reg)       # a fresh copy of the user's regulariser per solve
    # -- images: each normalised by its mean and spread, spline coefficients once ------------------------------
    t = time.perf_counter()
    ref, mov, I1, I2, fan = _image_stage(ref, mov, spacing, origin, normalize, data_mask)
    rect = None if fan is None else fan.rectangle
    timings["prefilter"] = time.perf_counter() - t

    # -- mesh ------------------------------------------------------------------------------------------------
    t = time.perf_counter()
    fe_mesh, stats, settings = _mesh_stage(ref, spacing, origin, mesh=mesh, element_size=element_size,
                                           margin=margin, strategy=strategy, initial=initial,
                                           regularizer=regularizer, allow_mesh_outside=allow_mesh_outside,
                                           rectangle=rect)
    locator = PointLocator(fe_mesh)
    timings["mesh"] = time.perf_counter() - t
    initial, fresh_note, term0 = _chosen_start(initial, ref, mov, I1, I2, fe_mesh, spacing, origin, offset, locator)

    # -- initial guess ---------------------------------------------------------------------------------------
    t = time.perf_counter()
    search = _search_stage(initial, ref, mov, I1, I2, fe_mesh, spacing, origin, regularizer=regularizer, offset=offset,
                           stats=stats, settings=settings, element_size=element_size, rectangle=rect)
    start = None if (noise := _noise_at_depth(search, args, ref.shape, spacing, origin)) is not None else initial_guess(
        initial, ref, mov, I1, I2, fe_mesh, spacing, origin, reg_factory, alpha=user_reg.alpha, regularizer=regularizer,
        strategy=strategy, offset=offset, stats=stats, settings=settings, element_size=element_size, margin=margin,
        maxiter=maxiter, tol=tol, linear_solver=linear_solver, blockmatch_options=blockmatch_options,
        coarse_to_fine=coarse_to_fine, rectangle=rect, search=search)
    if noise is not None or (search is None and (noise := _noise_at_depth(start, args, ref.shape, spacing, origin))):
        return _registered_crop(noise, args)    # no match at depth (the pyramid's search, or the paper's start): cut
    u0, stats = start.u0, start.stats
    timings.update(start.timings, initial=time.perf_counter() - t)

    # -- Gauss-Newton on the final mesh ----------------------------------------------------------------------
    t = time.perf_counter()
    solve_kw = dict(offset=offset, maxiter=maxiter, tol=tol, linear_solver=linear_solver)
    if strategy == "auto":
        st = (GN_STRAIN_TOL_TIGHT if user_reg.quadratic else GN_STRAIN_TOL) if strain_tol is None else float(strain_tol)
        solve_kw.update(mask_outside=True, tol=component_tol(tol, u0), strain_tol=st if st > 0 else None)
    def fine_solve(u, **kw):            # Gauss-Newton on the final mesh from the nodal displacement u
        return solve(I1, I2, fe_mesh, ref.shape, spacing, origin, reg_factory, u, locator=locator, **kw)
    sol = fine_solve(u0, callback=callback, term=term0, **solve_kw)
    timings.update(gauss_newton=time.perf_counter() - t, per_iteration=list(sol.gn.timings))

    # -- repair and check ------------------------------------------------------------------------------------
    t = time.perf_counter()
    notes, hops = [ENVELOPE_NOTE] * (envelope := orientation.is_envelope(ref)), np.zeros(fe_mesh.p.shape[1], int)
    if repair and strategy == "auto" and ref.shape[0] > 1 and not envelope:
        # the reseeded start is far from converged around the moved nodes: the tight strain tolerance
        tight = None if solve_kw.get("strain_tol") is None else min(solve_kw["strain_tol"], GN_STRAIN_TOL_TIGHT)
        sol, hops, notes = repair_peak_hopping(
            sol, lambda u: fine_solve(u, **dict(solve_kw, strain_tol=tight)), fe_mesh,
            stats.period if stats is not None else rf_period(ref, spacing),
            None if start.coarse_u0 is None else start.coarse_u0[0::2])
    notes += depth_fall_note(ref, spacing) + [fresh_note] * bool(fresh_note)   # echo weakening; started afresh
    marked, sol = lambda_bar_stage(sol, user_reg, notes, lambda u: fine_solve(u, callback=callback, **solve_kw),
                                   follows=lambda_bar_follows_data(strategy, regularizer, regularizer_options, maxiter)
                                   and not (envelope or any(hops)))       # R_P_sigma's lambda_bar from the data
    unrefined = (sol, u0, hops, list(notes))
    sol, u0, hops = refine_stage(sol, u0, hops, refine, reg_factory, I1, I2, dict(solve_kw, callback=callback),
                                 notes, timings, marked=marked, stats=stats)              # femreg.refine

    period = check_period(ref, spacing, stats) if ref.shape[0] > 1 and not envelope else None
    global_ncc = None if start.pyramid is None else start.pyramid.global_ncc

    def checked(s, start_u, h):
        # a refined result is judged on the unrefined cells (femreg.refine.parent_cells): the same limits hold
        groups = None if s.mesh is unrefined[0].mesh else parent_cells(unrefined[0].mesh, s.mesh)
        return check_result(s, start_u, h, ref.shape, spacing, period, global_ncc, groups=groups, envelope=envelope)
    check = checked(sol, u0, hops)
    if not check.success and sol is not unrefined[0]:
        # a refinement that fails the check is dropped for the unrefined result and its own verdict
        sol, u0, hops, notes = unrefined
        why = "; ".join(n for n in check.notes if not n.startswith("the pair is strongly decorrelated"))
        check = checked(sol, u0, hops)
        notes.append(f"refinement dropped (the refined result failed its check: {why})")
    timings.update(check=time.perf_counter() - t, total=time.perf_counter() - t_all)
    # -- result ----------------------------------------------------------------------------------------------
    notes += check.notes + orientation.period_notes(ref, period)    # a carrier outside clinical probes' band
    message = "; ".join([sol.gn.message] + notes) if notes else sol.gn.message
    if not check.success:   # the reasons first; the solver's own stop ("converged ...") is no verdict on the result
        message = (f"FAILED: {'; '.join(notes)} (Gauss-Newton stopped after {sol.gn.nit} iterations: "
                   f"{sol.gn.message.replace('converged: ', '')})")
    return _masked(with_refinement(RegistrationResult(
        sol.mesh, check.u, shape=ref.shape, spacing=spacing, origin=origin, regularizer=sol.reg.name,
        alpha=user_reg.alpha, success=check.success, status=sol.gn.status, message=message, nit=sol.gn.nit,
        energy_history=sol.gn.energy_history, ncc_before=check.ncc_before, ncc_after=check.ncc_after,
        timings=timings, blockmatch=start.blockmatch, solver_result=sol.gn, locator=sol.locator,
        quality=check.quality, strategy=strategy, alpha_effective=sol.reg.alpha, hop_gain=check.hop_gain,
        lambda_bar=getattr(sol.reg, "lambda_bar", None), started_afresh=bool(fresh_note)), sol),
        fan, data_mask)


autoalpha.ENGINE = register      # choose_alpha registers through this function (autoalpha never imports it)
