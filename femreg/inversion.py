r"""Shear-modulus images from a measured displacement: a finite-element inverse problem (``femreg.invert``).

The measured field is the registration's own FE field (or any callable), so the inversion runs on a quad mesh
without resampling images.  Unknown: the shear modulus :math:`\mu(x) > 0`, one value per element, parametrised by
:math:`\theta = \log\mu` (so :math:`\mu` stays positive without constraints).

Forward model (eq:cEq and eq:meq of the method paper, arXiv 2508.19086): find u with u = u_meas on the boundary
of the region and

.. math::
    \int_\Omega \mu\,\big(\bar\lambda\,\nabla\!\cdot u\,\nabla\!\cdot v + 2\,\nabla^s u : \nabla^s v\big)\,d\Omega = 0
    \qquad \forall v,\ v = 0 \text{ on } \partial\Omega,

i.e. :math:`\nabla\cdot(\mu A[u]) = 0` with :math:`A = \bar\lambda\,\nabla\!\cdot u\,I + 2\nabla^s u`.
``model="plane-stress"``: incompressible plane stress, :math:`\bar\lambda = 2`.  ``model="plane-strain"``:
nearly incompressible plane strain, :math:`\bar\lambda = 2\nu/(1-2\nu)` (99 at the default :math:`\nu = 0.495`),
the volumetric term with a one-point (reduced) rule so that bilinear quads do not lock (selective reduced
integration; Hughes, IJNME 15 (1980) 1413, doi:10.1002/nme.1620150914).  All boundary values are the measured
displacement, the usual choice when tractions are unknown (Doyley, Phys. Med. Biol. 57 (2012) R35,
doi:10.1088/0031-9155/57/3/R35).  With Dirichlet data everywhere, :math:`c\mu` gives the same u as :math:`\mu`:
the modulus is **relative** and is returned normalised so that its area-weighted **median over the region is 1**.

Measured on exact forward-model displacements (``forward.solve_elasticity``, P2 triangles; 30 x 30 mm around the
15 mm inclusion; contrast = mean mu of the elements fully inside / fully outside): plane stress HI 4.09-4.10 (true
4; 1 and 1.5 mm elements), SI 0.509 (0.5), mHI 2.01 (2); plane strain HI 4.14 with 1 mm elements but 4.31-4.37 with
1.5 mm (the reduced-integration model converges more slowly in h), SI 0.521; a uniform block gives a coefficient
of variation of 0.1-0.3 %.  On displacements of the 3D phantom a 2D model is itself an approximation: the
plane-stress inversion of the *true* 3D displacement gives a contrast of 2.2 for the 4-times-stiffer sphere.

3D data (a displacement callable ``(n, 3) -> (n, 3)`` with a region of three intervals, or a 3D registration
result: anything with a hexahedral ``mesh`` and ``displacement(points)``) are inverted with ``model="3d"``: the
same weak forms on trilinear hexahedra (MeshHex1 / ElementHex1), :math:`\bar\lambda = 2\nu/(1-2\nu)` with the
one-point volumetric rule, the TV over interior faces, and a sparse direct solver (:data:`LINEAR_SOLVER_3D`).
Two defaults differ from 2D, both because a volume's elevational (and lateral) displacement is measured far less
accurately than the axial one (the elevational beam, 1-3 mm, on planes 0.3-0.5 mm apart):

- Boundary values (``boundary=None``): with at least :data:`FITTED_MIN_ELEMENTS` elements across every axis the
  lateral and elevational boundary values are unknowns beside :math:`\theta`, fitted by the same misfit
  (``boundary="fitted"``: :math:`u_B = d_B + c\,g`, :math:`c = \bar\varepsilon h`; the adjoint gives
  :math:`\partial J/\partial u_B = (M r)_B/s^2 - K_{IB}^T\lambda_I` without another solve); the axial ones stay
  imposed.  Imposed noisy boundary values alone drive the modulus: the exact HI field with noise correlated over
  2 mm (1 / 5 / 20 um axial / lateral / elevational) on the boundary nodes only gives a background CV of 88 %,
  on the interior nodes only 8.5 %.  Thinner meshes keep the measured boundary (a fitted one has too few
  interior data to be fitted against; :data:`FITTED_MIN_ELEMENTS`).
- Misfit weights (``weights=None``): :data:`DEFAULT_WEIGHTS_3D` = (1, 0.1, 0.01): in a nearly incompressible
  solid :math:`\varepsilon_{zz} = -(\varepsilon_{xx} + \varepsilon_{yy})`, so the model fills in u_z from the
  in-plane data and needs the elevational data only as an anchor (exact data: contrast within 1 % of w_z = 0.1).
  A first inversion with these weights measures each component's noise as its RMS misfit at the interior nodes
  (the part of the data no modulus makes elastic), the lateral and elevational weights are lowered to
  :math:`w_x\sigma_x^2/\sigma_i^2` (never above the default nor below :data:`WEIGHT_FLOOR_3D`), and a second
  inversion uses them (twice the time where they change or ``uncertainty`` is asked for).

Explicit ``weights`` or ``boundary`` switch either off (``boundary="measured", weights=(1, 0.1, 0.1)`` is the
former 3D default).  Measured on the exact displacement of the paper's 3D phantom (benchmarks/inversion3d.py;
30 x 30 mm around the sphere, z +-10 mm, beta 1e-3, 2 mm elements; the former defaults in brackets): contrast
4.14 (4.18) for HI (true 4), 1.99 (2.01) mHI (2), 0.56 (0.55) SI (0.5), HOM uniform within a CV of 0.03 %
(1.8 %), and 4.09 (4.05) for HI with 1 / 5 / 5 um white noise.  With noise correlated over 3-12 mm
(``--correlated``; 1-2 / 5-10 / 5-50 um): HI 3.82-4.08 with a background CV of 0.9-4.1 % (3.70-4.85 with
21-633 %).  On the registered volume (``benchmarks/volume_study.py``: RF volumes of the 3D HI phantom, 0-72 x
+-22 x +-10 mm, inverted over x 15-45, y +-15, z +-8 mm; docs/inversion.md): 3.91 with a background CV of 1.5 %
(2.43 with 98 %), as the registered in-plane components with the exact u_z (3.91): u_z no longer limits it
(a crop x 13-47, y +-17 mm: 3.49 with 2.3 %, 4.59 with 44 %).
The 2D model's mismatch on 3D data (plane stress of the exact 3D displacement: 2.2) is gone.  Over the paper's
imaged area (x 2-70 mm, y +-22 mm, z +-10 mm, 2 mm elements, 26.6 k DOFs): HI 4.38 (4.46), SI 0.517 (0.508).
The uncertainty is the same Laplace approximation (with the fitted boundary held at its values) while
du/dtheta fits :data:`LAPLACE_DENSE_LIMIT`, else only the constrained mask.

Objective (minimised over :math:`\theta`, one value per element):

.. math::
    J(\theta) = \frac{1}{2 s^2} \int_\Omega w_x (u_x - d_x)^2 + w_y (u_y - d_y)^2\,d\Omega
              + \beta\,\frac{h}{|\Omega|}\sum_{\text{interior edges } f} \ell_f \sqrt{[\theta]_f^2 + \delta^2}

with d the measured displacement (nodal interpolant), u = u(θ) the model's, :math:`s^2 = |\Omega|\,(\bar\varepsilon
h)^2` (:math:`\bar\varepsilon` the RMS strain of d, h the mean element size: the misfit is measured in units of
the displacement change across one element), and the second term the total variation of the piecewise-constant
:math:`\log\mu` (its exact TV for :math:`\delta = 0`), made dimensionless by :math:`h/|\Omega|`.  ``regularization=
"tikhonov"`` uses :math:`\beta\,\frac{h^2}{2|\Omega|}\sum_f (\ell_f/d_f)[\theta]_f^2` (:math:`d_f` the distance of
the two element centres), a discrete :math:`\int|\nabla\theta|^2`.  2D TV is debiased (:data:`TV_REWEIGHT`): after the
:math:`\beta` rule one more solve at the chosen :math:`\beta` divides each edge's :math:`\ell_f` by
:math:`1 + |[\theta]_f|/\kappa` (:math:`\kappa` = 1), the log penalty :math:`\kappa\log(1+|[\theta]|/\kappa)` linearised
at the plain-TV solution: plain TV shrank soft plane-strain disks to 1.3-1.6 x their modulus (docs/inversion.md).
Then a region debias refit (:data:`TV_REFIT`): the solution's regions of nearly constant :math:`\theta` get one value
each, fitted to the misfit alone where the data constrain it (the compressed-sensing debiasing step), which lifts
the TV shrinkage that remained (registered soft plane-strain disks read 1.1-1.3 x the truth without it).

Weights: :data:`DEFAULT_WEIGHTS` = (1, 0.1) (axial, lateral).  Ultrasound measures the lateral displacement far
less accurately than the axial one (coarser lateral sampling and PSF; in the paper's 3D HI table the relative
lateral error of R_P_sigma is 9 % against 0.1 % axially), so the axial data lead.  w_y = 0.1 is a round choice
that keeps the lateral information (the lateral boundary data enter the model in any case); on the registered 3D
phantom, w_y = 0.01 and 0.1 gave contrasts within 0.1 of each other for the momentum regularisers at beta 0.01.

Gradient by the adjoint method: :math:`K_{II}(\theta)\,u_I = -K_{IB}\,d_B`, :math:`K_{II}\lambda = \partial J/\partial
u_I`, :math:`\partial J/\partial\theta_e = -\mu_e\,\lambda^T K_e u` (:math:`K_e` the unit-modulus element
matrix), one factorisation (banded Cholesky) for both solves.  Optimiser: L-BFGS-B (SciPy) with :math:`|\theta| \le`
:data:`THETA_BOUND`.

Choice of :math:`\beta` (``beta=None``), default ``beta_method="dof"``: solves run over :data:`BETA_GRID`
(largest first, each warm-started from the previous one); at each :math:`\beta` the number of parameters the data
determine, :math:`\gamma = \mathrm{tr}(H_d H^{-1})` (:math:`H_d` the Gauss-Newton Hessian of the misfit, H that of
J; MacKay, Neural Comput. 4 (1992) 415), is computed, and the chosen :math:`\beta` is the grid value whose
:math:`\gamma` is nearest

.. math::
    \gamma^* = \frac{|\Omega|}{A}\,\Big(\frac{h_0}{h}\Big)^p

with A = :data:`DOF_AREA` = 20 mm^2, :math:`h_0` = :data:`DOF_ELEMENT_SIZE` = 1.4 mm, p = :data:`DOF_EXPONENT` = 1
and h the mean element size (at most half the elements; on the default grid, when the largest :math:`\beta` already
gives more, up to :data:`DOF_UP_STEPS` half decades above it are tried).  :math:`\gamma` grows as :math:`\beta`
falls.  The target is the geometric mean of one parameter per 20 mm^2 and one per ten elements (the two coincide at
:math:`h = \sqrt 2` mm): a registration's element size follows the speckle size, so finer elements carry
displacement data of finer resolution, but each node's error is correlated with its neighbours' over a length, so
the information grows more slowly than the element count.  Where the nearer grid value is the smaller of the two
about the target and its image fails the tests of :func:`_overfit_reason`, the larger is taken if its image passes
them (:data:`DOF_STEP_BACK`).  Measured on the fixed-beta sweeps of
benchmarks/inversion.py (main and held-out sets, benchmarks/inversion_beta_sweep.py): area / :math:`\gamma` at the
truth-best :math:`\beta` falls as :math:`h^{1.0-1.2}` (median 16-17 mm^2 on 1.4-1.5 mm elements, 7 mm^2 on
0.68 mm ones).  The per-area target alone (``beta_method="dof-area"``, the former default) put the fine 12 / 15 MHz
meshes at :math:`\beta` 0.3-1 (truth-best 0.03), flagged at the grid's top; one per ten elements went too small.
The rule does not read the noise: exact or much noisier data than a registration's deserve another :math:`\beta`
(pass ``beta=``); in 3D the target stays one parameter per :math:`(4.5\ \mathrm{mm})^3` (not re-measured against
the element size).  A :math:`\beta` on the last grid value, or on the first with a modulus image that is not flat,
is flagged.  A solve that does not converge (L-BFGS-B's ``maxiter``) ends the sweep at the beta before it; on the
grid's first beta (an image that is not flat) that is flagged as a target the rule could not bracket (soft
plane-strain disks the data hardly determine: converged, the next beta gave 0.3 x the true contrast on the L3
cases of benchmarks/inversion.py).

``beta_method="growth"``: the last :math:`\beta` before the regulariser R starts to grow quickly as
:math:`\beta` falls, :math:`-\Delta\log R/\Delta\log\beta >` :data:`GROWTH_RATE` (R up by more than 1.3 x per half
decade); a cousin of the quasi-optimality criterion (Bauer & Lukas, Math. Comput. Simul. 81 (2011) 1795,
doi:10.1016/j.matcom.2011.01.016).

``beta_method="l-curve"``: an L-curve rule.  Solves run over :data:`BETA_GRID` (half-decade
steps, largest first, each warm-started from the previous one) and record the misfit :math:`\phi` and the
regulariser R.  Along the L-curve (log R against log :math:`\phi`) the slope
:math:`s = \Delta\log R / (-\Delta\log\phi)` between neighbouring :math:`\beta` is small while lowering
:math:`\beta` buys a large drop of the misfit; it exceeds :data:`LCURVE_SLOPE` = 1 at the corner, where the
modulus starts to follow noise (R grows faster than the misfit falls, in relative terms).  The chosen
:math:`\beta` is the last one before the first step with :math:`s >` :data:`LCURVE_SLOPE` (the sweep stops there),
or the smallest of the grid if there is none; the sweep also stops, keeping the previous :math:`\beta`, when a
solve does not converge within ``maxiter`` or drives :math:`|\log\mu|` to :data:`THETA_BOUND` (the modulus
has started to fit noise).  Measured: exact 2D forward-model data keep the smallest
:math:`\beta` (1e-4; the slope stays below 0.3), registered 3D-phantom displacements stop at 0.003-0.1,
mostly 0.01-0.03.  The L-curve method: Hansen, SIAM Rev. 34 (1992) 561, doi:10.1137/1034115.  Pass
``beta=`` to override.

Model choice (``model="auto"``, the default): the lateral-to-axial strain ratio of the data,
:func:`strain_ratio`, against the 2D model's :math:`\bar\lambda/(\bar\lambda+2)` (:func:`model_ratio`); see
:func:`invert`.  On registered RF pairs of plane-strain truths it measures 0.94-1.01 (R_P_sigma, the 47 of
benchmarks/inversion.py; R_P_eps 0.97) and 0.78-0.88 (R_eps, whose isotropic smoothing shrinks the lateral strain);
on plane-stress truths 0.45-0.52.  A given model that the data's ratio contradicts (``model="plane-strain"`` on an
R_eps field) is flagged.

Uncertainty: the Laplace std of a registered displacement is multiplied by :data:`REGISTERED_SIGMA` x
:data:`DOF_ELEMENT_SIZE` / h (:func:`_registered_sigma`; the registration's errors are correlated over about 2.4 mm,
whatever its element size).  That calibration holds for a few inclusions in a uniform background; the std is the
noise's spread at the chosen beta and misses the regulariser's bias where the stiffness varies everywhere.  A 2D TV
image of more than :data:`CALIBRATION_MAX_REGIONS` regions besides the largest (:func:`_calibration_regions`) is
such tissue: ``uncertainty_calibrated`` is False with a note in ``notes`` (not a flag: the modulus is what TV gives
for such data), and the std gets a bias term, :data:`UNCALIBRATED_SPREAD` x the image's robust spread of log mu in
quadrature.  A calibrated 2D TV std is widened to at least the background's own scatter (:data:`SCATTER_FLOOR`,
:func:`_scatter_factor`): the robust spread of log mu over the largest region against the RMS of its Laplace std.

Never silently wrong: ``success`` is False, with the reasons in ``flags`` and ``message``, when the optimiser
fails, :math:`\beta` lands on the smallest value of its grid (or on the largest while the image is not flat:
5-95 % spread of mu above :data:`CONTRAST_REGION`), :math:`|\log\mu|` reaches
:data:`THETA_BOUND`, the chosen model's strain ratio differs from the data's by more than
:data:`RATIO_TOLERANCE` (under ``model="auto"``: a ratio farther than :data:`AUTO_RATIO_TOLERANCE` from every
model, e.g. a lateral displacement that is noise), the model's own field expands laterally less than the data in
every quadrant of the image by more than :data:`MODEL_RATIO_TOLERANCE` (:func:`_lateral_shortfall`: data that are
no displacement of the model, such as an R_eps registration's), the misfit stays well above the noise level
(:data:`MISFIT_LIMIT`, in units of the model's strain: noise inflates the data's own), or a stiff (soft) region
strains more (less) than the background (:data:`CONTRADICTION_MARGIN`), or, for any contrast of at least
:data:`RANKED_CONTRAST`, the stiffer part of the image strains more than its softer part (:data:`RANKED_MARGIN`;
:func:`_contradiction`), or, in a 2D TV image whose region refit was not applied (more than
:data:`TV_REFIT_MAX_REGIONS` regions), regions whose modulus step the axial strain does not show cover more than
:data:`UNSUPPORTED_AREA` of it (:func:`_unsupported_regions`; elsewhere such regions leave a note).  Uncertainty: a Laplace approximation (``uncertainty``, ``constrained``).
Absolute moduli: ``reference=`` (kPa).  Boundary conditions: ``boundary=`` (:data:`BOUNDARIES`); the measured
displacement on the whole boundary stays the default of 2D data (benchmarks/inversion.py, docs/inversion.md).

Public names: :func:`invert`, :class:`InversionResult`, :func:`load_inversion`, :func:`modulus_contrast`,
:func:`is_inversion_file`, :func:`strain_ratio`, :func:`model_ratio`, :data:`MODELS`.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .errors import FileFormatError, InputError, counted, pass_as
from .fields import inner_elements, lateral_ratio
from .linsolve import SPDSolver, single_blas_thread
from .material import MODELS
from .material import lambda_bar as material_lambda_bar
from .material import lambda_bar_from_ratio, model_ratio

__all__ = ["invert", "InversionResult", "load_inversion", "modulus_contrast", "is_inversion_file", "lambda_bar",
           "strain_ratio", "model_ratio", "AUTO_RATIO",
           "MODELS", "DEFAULT_WEIGHTS", "BETA_GRID", "LCURVE_SLOPE", "GROWTH_RATE", "DOF_AREA", "BETA_METHODS",
           "MISFIT_LIMIT", "DOF_ELEMENT_SIZE", "DOF_EXPONENT", "REGISTERED_SIGMA", "TV_REWEIGHT",
           "TV_REWEIGHT_STEPS", "TV_BREGMAN", "TV_BREGMAN_FRACTION", "TV_BREGMAN_START", "TV_REFIT",
           "TV_REFIT_MAX_REGIONS",
           "TV_REFIT_MIN_ELEMENTS", "TV_REFIT_SIGMA", "TV_REFIT_MAX_SHIFT", "TV_REFIT_CAP", "TV_REFIT_MODE",
           "TV_REFIT_STD", "LAYER_CONTRAST", "LAYER_EXPLAINED", "LAYER_MIN_AREA", "CALIBRATION_MAX_REGIONS",
           "CALIBRATION_LEVEL", "CALIBRATION_MIN_AREA", "UNCALIBRATED_SPREAD", "SCATTER_FLOOR",
           "SCATTER_FLOOR_REFITTED", "SCATTER_FLOOR_MIN_ELEMENTS", "SUPPORT_LEVEL", "SUPPORT_FRACTION",
           "UNSUPPORTED_AREA"]

#: Misfit weights (axial w_x, lateral w_y); see the module docstring.
DEFAULT_WEIGHTS = (1.0, 0.1)
#: beta values tried by the default rule, largest first (half-decade steps).
BETA_GRID = tuple(float(10.0 ** e) for e in np.arange(-1.0, -4.01, -0.5))
#: L-curve slope at which the ``beta_method="l-curve"`` rule stops (module docstring).
LCURVE_SLOPE = 1.0
#: Growth rate -d log R / d log beta at which the default rule stops: a factor 1.3 per half decade.
GROWTH_RATE = float(np.log(1.3) / np.log(np.sqrt(10.0)))
#: Rules for beta (``beta_method``); the first is the default.  "dof-area" is the former default (the target per
#: area alone).
BETA_METHODS = ("dof", "dof-area", "growth", "l-curve")
#: Default rule: beta at which the data determine gamma = tr(H_d H^-1) = area / DOF_AREA * (DOF_ELEMENT_SIZE /
#: h)^DOF_EXPONENT parameters (module docstring); "dof-area": area / DOF_AREA whatever the element size.
DOF_AREA = 20.0
#: Element size (mm) at which the default rule's target is one parameter per DOF_AREA.
DOF_ELEMENT_SIZE = 1.4
#: Power of DOF_ELEMENT_SIZE / h in the default rule's target (0: per area, 2: per element).
DOF_EXPONENT = 1.0
#: Half-decade steps the default rule may take above the largest beta of the grid.
DOF_UP_STEPS = 2
#: The dof rules' target lies between two grid betas, the nearer taken.  Where the nearer is the bracket's smaller
#: beta and its debiased image shows more than the data support (its modulus contradicts the axial strain, its TV
#: solution is not a few regions: :data:`CALIBRATION_MAX_REGIONS`, or unsupported regions cover more than
#: :data:`UNSUPPORTED_AREA` of an image the refit skipped), the bracket's larger beta is taken if its image shows none
#: of these (docs/inversion.md, "The beta rule's step back and unsupported regions").  False: always the nearer.
DOF_STEP_BACK = True
#: Smoothing of the TV term, in log-modulus units (a jump of 0.01 = 1 % in mu is "small").
TV_DELTA = 1e-2
#: Bound on |log mu| during the optimisation (mu within a factor e^7 ~ 1100 of the start).
THETA_BOUND = 7.0
#: Poisson ratio of the plane-strain model by default.
DEFAULT_POISSON = 0.495
#: Boundary conditions of the forward model (:func:`_dirichlet_dofs`).
BOUNDARIES = ("measured", "axial-sides", "free-sides", "fitted")
#: Strain ratios at or below / at or above which ``model="auto"`` picks plane stress / plane strain.
AUTO_RATIO = (0.55, 0.9)
#: An explicit model is flagged when the data's strain ratio differs from the model's by more than this: about 2 x
#: the largest difference between a registered field's ratio and its truth's (0.047 over the 94 registrations of
#: benchmarks/inversion.py, R_P_sigma, every probe, 15-30 dB, 1-4 %; docs/inversion.md).  Beyond it the lateral
#: displacement is biased (R_eps registrations: 0.85 on a plane-strain truth) or the model is wrong, and the
#: inversion may be too (a stiff disk 30 % high with the plane-strain model on the R_eps field).
RATIO_TOLERANCE = 0.1
#: Under ``model="auto"`` (which follows the data's ratio between the two models) a ratio farther than this from
#: the nearest model is flagged: one no 2D model reaches (out-of-plane motion, a lateral displacement that is noise).
AUTO_RATIO_TOLERANCE = 0.2
#: The forward model's own displacement at the solution (``u_model``, from the measured boundary values) must
#: expand laterally as the data do: flagged when, in each of the four quadrants of the inner elements, its mean
#: lateral/axial strain ratio falls short of the data's by more than this fraction (:func:`_lateral_shortfall`).
#: The lateral displacement weighs 0.1 in the misfit, so a modulus can fit the axial strain with a lateral strain
#: that the data do not show; then the data are no displacement of the model (R_eps registrations, whose smoothing
#: shrinks the lateral strain around an inclusion and raises it inside) and the modulus that fits their axial part
#: is off: R_eps soft disks came out 2-3 x the truth, stiff ones 1.24 x, unflagged.  About 2 x the largest quadrant
#: shortfall of the main set of benchmarks/inversion.py (0.014, registered with the defaults; the smallest of the four
#: at most -0.002, and at most +0.00002 on all 108 default rows: no false flag); the 22 R_eps results off the truth
#: by more than 15 %: 0.051-0.096, all flagged (docs/inversion.md).
MODEL_RATIO_TOLERANCE = 0.03
#: mu above this (or below its inverse) marks a stiff (soft) region for the strain-consistency check.
CONTRAST_REGION = 1.5
#: Relative strain difference beyond which a region's modulus contradicts its strain (the wrong side).
CONTRADICTION_MARGIN = 0.1
#: The two-part test of :func:`_contradiction` splits the image at the middle of this (area-weighted) percentile
#: range of log mu ...
RANKED_RANGE = (0.01, 0.99)
#: ... runs on images whose range of mu spans at least this factor (below it the image is flat for this purpose) ...
RANKED_CONTRAST = 1.05
#: ... and flags when the stiffer part's mean |e_xx| exceeds the softer part's by more than this fraction.
RANKED_MARGIN = 0.25
#: Layers (:func:`_layer_contradiction`): a step of the depth profile of the row-median modulus at least this
#: factor ...
LAYER_CONTRAST = 1.5
#: ... is flagged when the row-median axial strain moves by less than this fraction of it (in log): layers in
#: series carry one axial stress, so the stiffer layer strains less by about the modulus ratio.
LAYER_EXPLAINED = 0.1
#: Each side of the step holds at least this fraction of the inner elements' area.
LAYER_MIN_AREA = 0.2
#: Misfit (dimensionless, module docstring: units of the squared displacement change across one element) above
#: which the model is said not to explain the data: 4 x the largest misfit of the true field against a registered
#: one on benchmarks/inversion.py (5.4e-3: 3 MHz probe, 20 dB; 1.3e-4 to 1.9e-3 at 5.5-7.5 MHz).
MISFIT_LIMIT = 0.02
#: Factor on the Laplace standard deviation of a registered displacement (not of a callable's) on elements of
#: DOF_ELEMENT_SIZE, scaled by DOF_ELEMENT_SIZE / h (:func:`_registered_sigma`): the temperature 2 phi / (n - gamma)
#: takes the n nodal data as independent, but a registration's errors are correlated over neighbouring nodes (over
#: a length, about 1.7 x 1.4 = 2.4 mm here, not a number of elements: the fewer independent data per node, the
#: finer the mesh) and carry its regulariser's bias.  Measured on the main and held-out cases of
#: benchmarks/inversion.py (fixed-beta sweeps, benchmarks/inversion_beta_sweep.py) as the factor that puts 68 % of
#: the true log mu within +-1 sigma at the rule's beta (without the 1/h: 1.6 on the 1.4-1.5 mm meshes, 4.2 on 0.68 mm).
REGISTERED_SIGMA = 1.7
#: 2D total variation, debiased: after the beta rule, one more solve at the chosen beta with each edge's weight
#: divided by ``1 + |[log mu]| / TV_REWEIGHT`` (log-modulus units; None: plain TV).  The weights linearise the log
#: penalty ``kappa log(1 + |[log mu]| / kappa)``, one step of iteratively reweighted l1 (Candes, Wakin & Boyd,
#: J. Fourier Anal. Appl. 14 (2008) 877, doi:10.1007/s00041-008-9045-x): jumps much smaller than kappa (noise)
#: keep the TV weight, an inclusion's edge (``|log 4|`` = 1.39) costs 2.4 x less.  Plain TV shrinks every contrast by
#: a bias that scales as beta over the data's information on the inclusion's modulus, and a soft disk in plane
#: strain carries 3 x less of it than a stiff one (6 x less than a soft one in plane stress; docs/inversion.md):
#: its estimate came out 1.3-1.6 x the truth even from the exact displacement.
TV_REWEIGHT = 1.0
#: Passes of the reweighting (:data:`TV_REWEIGHT`), each from the last one's solution.  Measured on the six sets of
#: benchmarks/inversion.py (docs/inversion.md, "Contrast-preserving TV"): 2 passes gave 81/92 in the band against
#: 80/92 (held-out +1, the others unchanged; background CV unchanged, calibration within 1 point): not adopted,
#: the one case gained has a background CV of 52 %.
TV_REWEIGHT_STEPS = 1
#: Bregman iteration after the reweighted solve (Osher, Burger, Goldfarb, Xu & Yin, Multiscale Model. Simul. 4 (2005)
#: 460, doi:10.1137/040605412, their eq. 3.7-3.8): ``TV_BREGMAN`` further solves of misfit + beta_B (R(theta) -
#: p.theta), p = ``TV_BREGMAN_FRACTION`` x the subgradient of R at the previous iterate, beta_B = ``TV_BREGMAN_START``
#: x the rule's beta; with ``TV_BREGMAN_START`` != 1 the iteration starts from a plain solve at beta_B and stops at
#: the first iterate whose misfit is at most the rule's plain-TV misfit (a discrepancy stop that needs no noise
#: level).  0: off (default).  Measured (docs/inversion.md): one full step at the rule's beta brings main to 16/16
#: but collapses the registered soft disks of the L3 and large-radius paper pairs (0.002-0.42 of the truth), 79/92.
TV_BREGMAN = 0
TV_BREGMAN_FRACTION = 1.0
TV_BREGMAN_START = 1.0
#: Region debias refit after the debiased-TV solve (None: off), the debiasing step of compressed sensing (Figueiredo,
#: Nowak & Wright, IEEE J. Sel. Top. Signal Process. 1 (2007) 586, sec. IV-B: keep the support the l1 solution found,
#: refit its values without the penalty), with the TV solution's piecewise-constant partition as the support.  log mu
#: is quantised to multiples of ``TV_REFIT`` (log-modulus units) about its median; edge-connected elements of one
#: level form a region, regions of fewer than :data:`TV_REFIT_MIN_ELEMENTS` join the neighbour of nearest mean, the
#: largest region is the reference (J is blind to a constant).  Each other region gets one log mu value, fitted to the
#: misfit alone by Gauss-Newton (:func:`_region_refit`) where the data constrain it: its marginal std (the Laplace
#: temperature and the registered-field factor of :func:`_laplace`) at most :data:`TV_REFIT_SIGMA` and its change at
#: most :data:`TV_REFIT_MAX_SHIFT`; any other region keeps its TV values, so a poorly determined soft disk cannot
#: collapse.  Measured on the six sets of benchmarks/inversion.py (docs/inversion.md, "Region debias refit"): 79/92
#: -> 91/92 contrasts in the band, calibration and background CV not worse on any set.
TV_REFIT = 0.5
TV_REFIT_MIN_ELEMENTS = 4
#: The refit models a few lesions in a background: a TV solution split into more regions than this (besides the
#: reference) is not piecewise constant and keeps its TV values.  On the 92 disk pairs at most 7 regions (3 pairs
#: above 4); on heterogeneous tissue (benchmarks/heterogeneous.py, smooth random log E) 3-22, where a refit lowered
#: the correlation with the true log E on all 8 pairs (median 0.80 -> 0.77) and the calibration (25 -> 16 % within
#: +-1 sigma).
TV_REFIT_MAX_REGIONS = 5
TV_REFIT_SIGMA = 0.1
TV_REFIT_MAX_SHIFT = 0.5
#: Changes larger than TV_REFIT_MAX_SHIFT: "reject" (the region keeps its TV values, the others are refitted
#: again without it) or "clip" (the change clipped to +-TV_REFIT_MAX_SHIFT).
TV_REFIT_CAP = "reject"
#: The region model: "constant-fit" (default: each refitted region constant, fitted against the reference region
#: made constant too, which keeps its TV values in the result), "constant" (fitted against the reference's TV
#: values), "constant-all" (the reference constant in the result as well: background CV 0 and, with the element
#: model's std, 95 % within +-1 sigma on main) or "shift" (one shift per region, the TV shape inside kept: on the
#: exact soft disk of tests/test_inversion_refit.py 1.26 x the truth against 1.07 x).
TV_REFIT_MODE = "constant-fit"
#: True: a refitted region's uncertainty is the region model's (one std per region, :func:`_region_refit`), the
#: other elements' the Laplace std at the TV solution (whose misfit sets the temperature); False: the Laplace std of
#: the element model at the refitted solution everywhere (held-out: 86 % within +-1 sigma against 72 %).
TV_REFIT_STD = True
#: The Laplace std (``uncertainty``) is the noise's spread at the chosen beta, not the regulariser's bias; its
#: calibration (:data:`REGISTERED_SIGMA`) was measured on a few inclusions in a uniform background.  A 2D TV solution
#: (before the refit) split into more than this many regions besides the largest (:func:`_calibration_regions`:
#: the refit's partition at :data:`CALIBRATION_LEVEL`, a region at least :data:`CALIBRATION_MIN_AREA`) is not
#: piecewise uniform: the result's ``uncertainty_calibrated`` is False, a note says so, and the std gets the bias
#: term of :data:`UNCALIBRATED_SPREAD`.  Measured (docs/inversion.md, "Heterogeneous tissue"): 7 of the 8 registered
#: random-tissue pairs of benchmarks/heterogeneous.py (3-21 regions; the eighth has 3), 4 of 4 more drawn for the
#: check, 1 of the 94 registered disk pairs of benchmarks/inversion.py (0-5 regions; the one with 5, a soft L3 disk,
#: had 31 % of its true log mu within +-1 sigma); a bound of 5 missed a second tissue pair and found no disk.
CALIBRATION_MAX_REGIONS = 4
#: Quantisation level (log-modulus units) of the region count of :data:`CALIBRATION_MAX_REGIONS` (the refit's).
CALIBRATION_LEVEL = 0.5
#: Smallest region (mm^2, at least :data:`TV_REFIT_MIN_ELEMENTS` elements) the count of
#: :data:`CALIBRATION_MAX_REGIONS` keeps; smaller ones join a neighbour.  In elements alone the stiff disk on a
#: 0.46 mm L15 mesh had 7 regions (its specks around the disk); 2-8 mm^2 gave the same counts elsewhere.
CALIBRATION_MIN_AREA = 4.0
#: Where ``uncertainty_calibrated`` is False the std becomes sqrt(std^2 + (UNCALIBRATED_SPREAD x s)^2), s the
#: robust spread (1.4826 x median absolute deviation) of log mu over the constrained elements: the bias of a
#: disk-tuned TV solution on a field that varies everywhere grows with the field's own variation, which the image's
#: (shrunk) spread estimates.  Chosen on the 8 pairs of benchmarks/heterogeneous.py: true log E within +-1 sigma
#: 23 -> 62 % (mean over the pairs; per pair 26-99 %; 26 -> 67 % pooled over their elements); 4 pairs drawn for the
#: check: 15 -> 64 % (14 -> 57 % pooled); the exact displacements of the 8: 9 -> 61 % (docs/inversion.md).  None:
#: the note only.
UNCALIBRATED_SPREAD = 0.9
#: Scatter floor on a calibrated 2D TV uncertainty (:func:`_scatter_factor`): the std is multiplied by
#: max(1, s / r), s the robust spread (1.4826 x median absolute deviation) of log mu over the constrained elements
#: of the background (the largest region of the partition of :data:`CALIBRATION_MAX_REGIONS`), r the RMS of the
#: Laplace std over the same elements.  The Laplace std is the noise's spread at the chosen beta; a background that
#: is truly uniform but shows more scatter than that (the registration's texture passed on by the inversion) bounds
#: the error from below, from the data.  Never narrows the std; the modulus is untouched.  Measured on the six sets
#: of benchmarks/inversion.py (docs/inversion.md, "Scatter floor on the uncertainty"), true log mu within +-1
#: sigma: main 54.7 -> 65.4 %, held-out 72.8 -> 73.2, fresh 63.9 -> 69.8, fresh2 78.6 -> 79.8, fresh3 69.8 -> 70.5,
#: fresh4 73.6 -> 74.6 % (every set in the 55-80 % target); factor above 1 on 21 of the 94 pairs, at most 3.76.
#: False: off.
SCATTER_FLOOR = True
#: With :data:`SCATTER_FLOOR`: True, the factor widens every element's std, the refitted regions' one std per region
#: (:data:`TV_REFIT_STD`) included; False, only the elements that keep the Laplace std.  Measured: main 65.4 %
#: against 64.6 % (its lowest case 34 % against 25 %), fresh 69.8 against 69.6 %, the other sets the same.
SCATTER_FLOOR_REFITTED = True
#: Fewest background elements :func:`_scatter_factor` reads a spread from (fewer: factor 1).
SCATTER_FLOOR_MIN_ELEMENTS = 8
#: Strain support of the regions of a 2D TV image (:func:`_unsupported_regions`, the partition of
#: :data:`CALIBRATION_MAX_REGIONS` before the refit): a region at least :data:`CALIBRATION_MIN_AREA` whose mean log
#: mu lies at least SUPPORT_LEVEL from the largest region's ...
SUPPORT_LEVEL = 0.25
#: ... is unsupported when the log of its mean abs(e_xx) against the largest region's (stiff: less strain) is below
#: SUPPORT_FRACTION x its log-modulus step (0 or the wrong side included).  Measured (docs/inversion.md, "Never
#: silently wrong"): 0.19-1.9 on every supported region of the 94 disk pairs and the 14 curves; -0.14 to 0.05 on the
#: unsupported ones (the 10 dB soft disk's 234 mm^2 region at 1.71 x the background: -0.01).
SUPPORT_FRACTION = 0.1
#: Unsupported regions covering more than this fraction of the inner elements' area flag the result where the
#: region refit was not applied (more than :data:`TV_REFIT_MAX_REGIONS` regions: every level is the regulariser's);
#: otherwise, or smaller, they leave a note.  None: notes only.  Measured (docs/inversion.md): 0.345 on the 10 dB
#: soft disk (ratio 0.53, refit not applied: flagged); 0 on the one disk pair without the refit (fresh2's L15 x4);
#: 0.25-0.38 on four L3 plane-strain disks with the refit (notes; ratios 0.85-0.99): the area alone does not separate.
#: Random tissue (benchmarks/heterogeneous.py, 12 registered pairs, refit skipped on 10): 0.363 on one (flagged),
#: 0-0.099 on the others; 0.2 was set after seeing them (0.1 came within 0.001 of one).
UNSUPPORTED_AREA = 0.2
#: 2D TV with the region refit applied: a region of the TV solution whose modulus step the axial strain does not show
#: (:func:`_unsupported_regions`) takes the background's mean log mu, and the refit runs again against that
#: background (docs/inversion.md, "The beta rule's step back and unsupported regions").  False: such regions keep
#: their values (a note).
SUPPORT_MERGE = True
#: An element is constrained when its data information is at least this fraction of the median.
CONSTRAINED_INFO = 1e-2
_FORMAT = "femreg-inversion-1"
#: Misfit weights (axial, lateral, elevational) of 3D data before the noise rule (module docstring): the
#: elevational displacement is measured with the elevational beam (1-3 mm), coarser still than the lateral one,
#: and the nearly incompressible model fills it in from the in-plane strains (e_zz = -(e_xx + e_yy)).
DEFAULT_WEIGHTS_3D = (1.0, 0.1, 0.01)
#: 3D data with ``weights=None`` (default): the lateral and elevational weights are lowered to w_x sigma_x^2 /
#: sigma_i^2, sigma_i the RMS misfit of component i at the interior nodes after a first inversion with
#: DEFAULT_WEIGHTS_3D (the part of the data that no modulus makes elastic: its noise), never above the default
#: weight nor below this floor (a component must still anchor the model's field; 0.001 lets u_z drift by 3 x its
#: noise on exact-plus-noise data).
WEIGHT_FLOOR_3D = 0.003
#: Boundary values of 3D data by default (``boundary=None``): "fitted", unknowns fitted by the misfit beside the
#: modulus, because noise in imposed boundary values of u_z alone drives the modulus (module docstring).
BOUNDARY_3D = "fitted"
#: ``boundary=None`` fits the boundary of 3D data only with at least this many elements across every axis: a
#: fitted boundary needs interior data to be fitted against (exact HI displacement, 30 x 30 mm box, 2 mm
#: elements, 3 / 4 / 6 elements across z: contrast 3.60 / 3.89 / 4.04 fitted against 3.97 / 4.05 / 4.08 measured).
FITTED_MIN_ELEMENTS = 6
#: ``boundary="fitted"``: the components fitted (index >= this; 1 = lateral and elevational), the axial one
#: imposed (it is measured best and carries the load).
FITTED_FROM = 1
#: Names of the 3D strain components (``strain_measured`` columns) and their (i, j) index pairs.
STRAIN_COMPONENTS_3D = ("exx", "eyy", "ezz", "exy", "exz", "eyz")
STRAIN_COMPONENTS_3D_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: Element size (mm) of the hexahedral mesh over a callable's 3D region by default.
DEFAULT_ELEMENT_SIZE_3D = 2.0
#: Linear solver (:class:`femreg.linsolve.SPDSolver` method) of the 3D forward and adjoint solves: "auto" =
#: banded Cholesky (node planes across the longest axis, or RCM) while the band fits BAND_LIMIT, else "splu".
#: Measured on 8.4 k DOFs (16 x 16 x 11 nodes): banded 0.21 s per factorisation, SuperLU 0.38 s, PARDISO slower
#: over a whole inversion on 2 shared cores; on 26.6 k DOFs SuperLU 1.8 s, PARDISO 0.9 s ("pardiso").
LINEAR_SOLVER_3D = "auto"
#: The 3D Laplace approximation is dense (du/dtheta and the Hessian); above this many entries of du/dtheta only
#: the constrained mask is computed (column blocks of du/dtheta, never stored whole).
LAPLACE_DENSE_LIMIT = 30_000_000
#: Columns of the data Hessian per block of solves (:func:`_data_hessian`): two n_I x block arrays at a time.
HESSIAN_COLUMNS = 1024


def lambda_bar(model: str, poisson: float | None = None) -> float:
    r""":math:`\bar\lambda` of eq:cEq (:func:`femreg.material.lambda_bar`): plane stress 2 (incompressible) unless
    ``poisson`` is given, plane strain and ``"3d"`` :math:`2\nu/(1-2\nu)` with ``poisson`` default
    :data:`DEFAULT_POISSON`."""
    if poisson is None:
        poisson = 0.5 if model == "plane-stress" else DEFAULT_POISSON
    if model == "3d":      # 3D: lambda / mu = 2 nu / (1 - 2 nu), the plane-strain value
        return material_lambda_bar("plane-strain", poisson)
    return material_lambda_bar(model, poisson)


# ----------------------------------------------------------------------------------------------------------------
# forward model (scikit-fem) and its adjoint
# ----------------------------------------------------------------------------------------------------------------
def _unit_forms():
    """Deviatoric and volumetric parts of eq:cEq's bilinear form for mu = 1."""
    from skfem import BilinearForm
    from skfem.helpers import ddot, div, sym_grad

    @BilinearForm
    def shear(u, v, w):
        return 2.0 * ddot(sym_grad(u), sym_grad(v))

    @BilinearForm
    def volumetric(u, v, w):
        return div(u) * div(v)

    return shear, volumetric


def _elements(mesh):
    """(nodal element, element-constant element) of the inversion mesh: bilinear quads in 2D, trilinear hexahedra
    in 3D."""
    from skfem import ElementHex0, ElementHex1, ElementQuad0, ElementQuad1

    return (ElementHex1(), ElementHex0()) if mesh.p.shape[0] == 3 else (ElementQuad1(), ElementQuad0())


class _Model:
    """The discrete forward problem K(mu) u = 0, u_B = d_B on one mesh, with everything that does not depend on
    mu precomputed: K(mu) = sum_e mu_e K_e, its CSR data = ``A @ mu``.  Quads (2D) or hexahedra (3D); the same
    weak forms (:func:`_unit_forms`) in both."""

    def __init__(self, mesh, lam_bar: float, reduced_volumetric: bool, weights, boundary: str = "measured"):
        from skfem import Basis, BilinearForm, ElementVector, asm

        self.mesh = mesh
        self.dim = dim = mesh.p.shape[0]
        self.n_el = mesh.t.shape[1]
        e = ElementVector(_elements(mesh)[0])
        self.basis = Basis(mesh, e, intorder=2)
        shear, volumetric = _unit_forms()
        S = shear.elemental(self.basis)
        if reduced_volumetric:   # one-point rule at the element centre (reference square / cube [0, 1]^dim)
            vbasis = Basis(mesh, e, quadrature=(np.full((dim, 1), 0.5), np.array([1.0])))
        else:
            vbasis = self.basis
        V = volumetric.elemental(vbasis)
        if not (np.array_equal(S.indices, V.indices)):
            raise RuntimeError("element matrices of the two quadratures do not share DOF numbering")
        data = S.data + lam_bar * V.data                    # (Nbfun^2 * n_el,), element index fastest
        rows, cols = S.indices
        elem = np.tile(np.arange(self.n_el), data.size // self.n_el)
        N = self.basis.N
        # CSR structure of K and the map (entries -> CSR slots) x (element -> entries)
        probe = sp.csr_matrix((np.arange(1, data.size + 1, dtype=float), (rows, cols)), shape=(N, N))
        probe.sum_duplicates()
        pattern = sp.csr_matrix((np.ones(data.size), (rows, cols)), shape=(N, N))
        pattern.sum_duplicates()
        pattern.data = np.arange(pattern.nnz, dtype=float)
        slot = np.asarray(pattern[rows, cols]).ravel().astype(np.int64)
        self._A = sp.csr_matrix((data, (slot, elem)), shape=(pattern.nnz, self.n_el))
        self._pattern = pattern
        self._G = sp.csr_matrix((data, (elem, np.arange(data.size))), shape=(self.n_el, data.size))
        self._rows, self._cols = rows, cols
        self._data, self._elem = data, elem              # unit element matrices, for the Jacobian du/dtheta
        self.D = _dirichlet_dofs(self.basis, mesh, boundary)  # boundary DOFs carrying the measured data
        self.I = np.setdiff1d(np.arange(N), self.D)
        if self.I.size == 0:
            raise InputError("the inversion mesh has no interior nodes; use smaller elements or a larger region")
        # the interior-interior and interior-boundary blocks as fixed sparsity patterns whose data are CSR slots of
        # K (slot + 1, so that no stored value is 0): K_II.data = (A @ mu)[slots], no sparse slicing per solve
        tagged = pattern.copy()
        tagged.data = np.arange(1, pattern.nnz + 1, dtype=float)
        self._KII = tagged[self.I][:, self.I].tocsc()
        self._KIB = tagged[self.I][:, self.D].tocsr()
        self._sII = self._KII.data.astype(np.int64) - 1
        self._sIB = self._KIB.data.astype(np.int64) - 1
        # banded Cholesky (LAPACK pbtrf, femreg.linsolve): K_II is symmetric positive definite for mu > 0, and on
        # these meshes its bandwidth (reverse Cuthill-McKee, or row by row on a structured mesh) is ~2 x (nodes
        # across), so one factorisation costs n b^2 flops, less than SuperLU's general LU.  Not positive definite
        # (should not happen): SuperLU.
        xy = self.basis.doflocs[:, self.I]
        comp = np.arange(N)[self.I] % dim
        if dim == 2:
            self._solver = SPDSolver("cholesky", shift=0.0, upper=True, one_thread=False,
                                     orderings=(np.lexsort((comp, xy[1], xy[0])), np.lexsort((comp, xy[0], xy[1]))))
        else:   # a 3D band is ~(nodes across)^2 wide: banded while it fits, else sparse direct (femreg.linsolve)
            plane_orders = [np.lexsort((comp,) + tuple(xy[j] for j in range(3) if j != k) + (xy[k],))
                            for k in range(3)]
            self._solver = SPDSolver(LINEAR_SOLVER_3D, shift=0.0, upper=True, one_thread=False,
                                     orderings=plane_orders)

        @BilinearForm
        def weighted_mass(u, v, w):
            if dim == 2:
                return weights[0] * u[0] * v[0] + weights[1] * u[1] * v[1]
            return sum(weights[i] * u[i] * v[i] for i in range(dim))

        self.M = asm(weighted_mass, self.basis).tocsr()
        self.area = float(np.sum(self.basis.dx))

    def stiffness(self, mu):
        K = self._pattern.copy()
        K.data = self._A @ mu
        return K

    def solve(self, mu, d):
        """u (N,) with u_B = d_B and the LU factor of K_II."""
        k = self._A @ mu
        KIB = self._KIB.copy()
        KIB.data = k[self._sIB]
        KII = sp.csc_matrix((k[self._sII], self._KII.indices, self._KII.indptr), shape=self._KII.shape)
        lu = self._solver.factor(KII)
        u = d.copy()
        u[self.I] = lu.solve(-(KIB @ d[self.D]))
        return u, lu

    def boundary_coupling(self, mu):
        """K_IB(mu), sparse (n_I, n_D)."""
        KIB = self._KIB.copy()
        KIB.data = (self._A @ mu)[self._sIB]
        return KIB

    def dJ_dtheta(self, mu, u, lam):
        """-mu_e lam^T K_e u for every element (lam zero on the boundary)."""
        return -mu * (self._G @ (lam[self._rows] * u[self._cols]))


def _dirichlet_dofs(basis, mesh, boundary: str) -> np.ndarray:
    """DOFs with the measured displacement imposed: all boundary DOFs (``"measured"``), or on the lateral sides
    (y = min, max; in 3D also the elevational sides z = min, max; their edges on x = min, max excepted) only the
    axial component (``"axial-sides"``) or none (``"free-sides"``, traction-free there)."""
    D = basis.get_dofs().all()
    if boundary in ("measured", "fitted"):      # "fitted": the values are unknowns (_Problem), the DOFs the same
        return D
    p = mesh.p
    side = (np.isclose(p[1], p[1].min()) | np.isclose(p[1], p[1].max())) & \
        ~(np.isclose(p[0], p[0].min()) | np.isclose(p[0], p[0].max()))
    if p.shape[0] == 3:
        side |= (np.isclose(p[2], p[2].min()) | np.isclose(p[2], p[2].max())) & \
            ~(np.isclose(p[0], p[0].min()) | np.isclose(p[0], p[0].max()))
    nodes = np.flatnonzero(side)
    drop = basis.nodal_dofs[1:, nodes].ravel() if boundary == "axial-sides" else basis.nodal_dofs[:, nodes].ravel()
    return np.setdiff1d(D, drop)


class _Regularizer:
    """TV (or Tikhonov) of the element-wise log-modulus over interior edges, dimensionless (module docstring)."""

    def __init__(self, mesh, kind: str, h: float, area: float, delta: float = TV_DELTA):
        from skfem import InteriorFacetBasis

        # 3D: faces instead of edges, ``length`` their areas, ``area`` the volume (the scale stays dimensionless)
        sides = [InteriorFacetBasis(mesh, _elements(mesh)[1], side=s) for s in (0, 1)]
        self.a, self.b = sides[0].tind, sides[1].tind
        self.length = np.asarray(sides[0].dx.sum(axis=1), float)
        c = mesh.p[:, mesh.t].mean(axis=1)
        self.dist = np.linalg.norm(c[:, self.a] - c[:, self.b], axis=0)
        self.kind = kind
        self.delta = float(delta)
        self.scale = h / area if kind == "tv" else 0.5 * h * h / area
        self.n_el = mesh.t.shape[1]
        self.base_length = self.length.copy()
        self.linear = None          # Bregman: the subgradient p of R at the previous iterate, R(theta) - p.theta

    def reweight(self, theta, kappa):
        """Edge weights 1 / (1 + |[theta]| / kappa) (:data:`TV_REWEIGHT`): the log penalty kappa log(1 + |[theta]| /
        kappa) linearised at ``theta``; None restores plain TV."""
        if kappa is None:
            self.length = self.base_length.copy()
        else:
            j = np.abs(theta[self.a] - theta[self.b])
            self.length = self.base_length / (1.0 + j / kappa)

    def __call__(self, theta):
        j = theta[self.a] - theta[self.b]
        if self.kind == "tv":
            s = np.sqrt(j * j + self.delta ** 2)
            val = self.scale * float(np.sum(self.length * (s - self.delta)))
            gj = self.scale * self.length * j / s
        else:
            c = self.length / self.dist
            val = self.scale * float(np.sum(c * j * j))
            gj = 2.0 * self.scale * c * j
        g = np.bincount(self.a, gj, self.n_el) - np.bincount(self.b, gj, self.n_el)
        if self.linear is not None:
            val -= float(self.linear @ theta)
            g = g - self.linear
        return val, g

    def hessian(self, theta, sparse: bool = False):
        """(n_el, n_el) Hessian of the (smoothed) regulariser at ``theta``: dense, or a sparse matrix."""
        j = theta[self.a] - theta[self.b]
        if self.kind == "tv":
            hj = self.scale * self.length * self.delta ** 2 / (j * j + self.delta ** 2) ** 1.5
        else:
            hj = 2.0 * self.scale * self.length / self.dist
        n = self.n_el
        D = sp.csr_matrix((np.r_[np.ones(j.size), -np.ones(j.size)],
                           (np.r_[np.arange(j.size), np.arange(j.size)], np.r_[self.a, self.b])), shape=(j.size, n))
        out = (D.T @ sp.diags(hj) @ D).tocsr()
        return out if sparse else out.toarray()


class _Problem:
    """J(theta) = misfit + beta R, with its adjoint gradient (module docstring).

    ``fit_boundary``: the boundary values are unknowns too, u_B = d_B + c g (``c`` the displacement scale
    sqrt(s^2 / |Omega|), g dimensionless), fitted by the same weighted misfit (:data:`BOUNDARY_3D`); the
    optimiser then runs over (theta, g), and :attr:`g` keeps the latest fitted values, so that ``misfit``,
    :attr:`dirichlet` and everything evaluated at a theta use the boundary fitted with it."""

    def __init__(self, model: _Model, reg: _Regularizer, d, s2, fit_boundary: bool = False):
        self.model, self.reg, self.d, self.s2 = model, reg, d, s2
        self.n_eval = 0
        # the fitted boundary DOFs (positions in model.D): the components other than the axial one
        comp = np.empty(model.basis.N, int)
        for c in range(model.dim):
            comp[model.basis.nodal_dofs[c]] = c
        self.fit = np.flatnonzero(comp[model.D] >= FITTED_FROM) if fit_boundary else np.zeros(0, int)
        self.n_b = self.fit.size
        self.scale = float(np.sqrt(s2 / model.area))
        self.g = np.zeros(self.n_b)

    @property
    def dirichlet(self):
        """The displacement whose boundary values the model takes: the data, or the fitted boundary."""
        if not self.n_b:
            return self.d
        b = self.d.copy()
        b[self.model.D[self.fit]] += self.scale * self.g
        return b

    def misfit(self, theta):
        u, _ = self.model.solve(np.exp(theta), self.dirichlet)
        r = u - self.d
        return 0.5 * float(r @ (self.model.M @ r)) / self.s2, u

    def evaluate(self, theta, beta, g=None):
        """(J, dJ/dtheta, misfit, R, u); with a fitted boundary and ``g`` given, at that boundary, and the
        gradient is dJ/d(theta, g)."""
        self.n_eval += 1
        mu = np.exp(theta)
        if g is not None:
            self.g = np.asarray(g, float)
        u, lu = self.model.solve(mu, self.dirichlet)
        r = u - self.d
        Mr = self.model.M @ r
        phi = 0.5 * float(r @ Mr) / self.s2
        lam = np.zeros_like(u)
        lam[self.model.I] = lu.solve(Mr[self.model.I] / self.s2)
        grad = self.model.dJ_dtheta(mu, u, lam)
        R, gR = self.reg(theta)
        grad = grad + beta * gR
        if g is not None and self.n_b:
            # u_I = -K_II^-1 K_IB u_B: dJ/du_B = (M r)_B / s^2 - K_IB^T lam_I (lam the adjoint above)
            gb = Mr[self.model.D] / self.s2 - self.model.boundary_coupling(mu).T @ lam[self.model.I]
            grad = np.r_[grad, self.scale * gb[self.fit]]
        return phi + beta * R, grad, phi, R, u


class _SweepBar:
    """The progress bar of :func:`invert`: one step per beta value of the sweep (its total the number of betas the
    sweep may solve; a sweep that ends at its chosen beta ends the bar there), the current beta and its L-BFGS-B
    iteration beside it, redrawn at most every :attr:`every` s.  ``update`` is the optimiser's per-iteration
    call (:func:`_optimise`)."""

    every = 0.2

    def __init__(self, n_beta: int, maxiter: int):
        from .progress import bar

        self.bar = bar(total=int(n_beta), desc="invert", unit="beta")
        self.maxiter, self.beta, self.it, self.shown = int(maxiter), None, 0, 0.0

    def start(self, beta) -> None:
        """A solve at ``beta`` begins."""
        self.beta, self.it = float(beta), 0
        self._show(force=True)

    def update(self, n: int = 1) -> None:
        self.it += n
        self._show()

    def _show(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self.shown >= self.every:
            self.bar.set_postfix_str(f"beta {self.beta:.3g}, iteration {self.it} of at most {self.maxiter}")
            self.shown = now

    def done(self) -> None:
        """The solve at the current beta ended."""
        self.bar.update(1)

    def extend(self, n: int = 1) -> None:
        """``n`` more betas to solve (the sweep goes past its grid)."""
        self.bar.total += n
        self.bar.refresh()

    def close(self) -> None:
        planned = self.bar.total
        if self.bar.n < self.bar.total:     # ended at its chosen beta: the rest was not needed
            self.bar.total = self.bar.n
        # a count that ends below the total shown before says why (a log reads "1/7", then "done, 2/2")
        self.bar.set_postfix_str(f"{self.bar.n} beta value(s) solved" + (
            f" of up to {planned}: the sweep stopped at its chosen beta" if self.bar.n < planned else ""),
            refresh=False)
        self.bar.close()


def _optimise(problem: _Problem, theta0, beta, *, maxiter, gtol, progress=None):
    """L-BFGS-B on J(theta); returns (theta, info dict with history)."""
    from scipy.optimize import minimize

    cache = {}
    history = []
    n = theta0.size
    fit = problem.n_b > 0     # a fitted boundary: x = (theta, g), from the problem's current g

    def split(x):
        return (x[:n], x[n:]) if fit else (x, None)

    def evaluate(x):
        theta, g = split(x)
        return problem.evaluate(theta, beta, g)

    def fun(x):
        J, g, phi, R, _ = evaluate(x)
        if not np.isfinite(J) or not np.all(np.isfinite(g)):
            raise FloatingPointError("non-finite objective")
        cache["last"] = (x.copy(), J, phi, R)
        return J, g

    def callback(xk):
        t, J, phi, R = cache["last"]
        if not np.array_equal(t, xk):
            J, _, phi, R, _ = evaluate(xk)
        history.append((J, phi, R))
        if progress is not None:
            progress.update(1)

    bounds = [(-THETA_BOUND, THETA_BOUND)] * n + [(None, None)] * problem.n_b
    x0 = np.r_[theta0, problem.g] if fit else theta0
    try:
        res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=bounds, callback=callback,
                       options={"maxiter": int(maxiter), "gtol": gtol, "ftol": 1e-12, "maxcor": 20})
    except (FloatingPointError, RuntimeError, np.linalg.LinAlgError) as exc:
        x = cache["last"][0] if "last" in cache else x0
        theta, g = split(x)
        if fit:
            problem.g = g.copy()
        return theta, {"success": False, "message": f"optimisation failed: {exc}", "nit": len(history),
                       "history": history, "boundary": None if g is None else g.copy()}
    msg = res.message if isinstance(res.message, str) else res.message.decode()
    theta, g = split(res.x)
    if fit:
        problem.g = g.copy()
    return theta, {"success": bool(res.success), "message": msg, "nit": int(res.nit), "history": history,
                   "n_eval": int(res.nfev), "boundary": None if g is None else g.copy()}


# ----------------------------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------------------------
def _tensor_mesh(x0, x1, y0, y1, h):
    from skfem import MeshQuad1

    hx, hy = h
    nx = max(2, int(round((x1 - x0) / hx)))
    ny = max(2, int(round((y1 - y0) / hy)))
    return MeshQuad1.init_tensor(np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1))


def _check_region(region):
    try:
        (x0, x1), (y0, y1) = region
        x0, x1, y0, y1 = (float(v) for v in (x0, x1, y0, y1))
    except (TypeError, ValueError):
        raise InputError(f"region must be ((x0, x1), (y0, y1)) in mm, got {region!r}") from None
    if not all(np.isfinite(v) for v in (x0, x1, y0, y1)) or x1 <= x0 or y1 <= y0:
        raise InputError(pass_as(f"region must be ((x0, x1), (y0, y1)) mm with x0 < x1 and y0 < y1, got {region!r}",
                                 f"--region X0 X1 Y0 Y1 needs X0 < X1 and Y0 < Y1 (mm), got {x0:g} {x1:g} {y0:g} "
                                 f"{y1:g}"))
    return x0, x1, y0, y1


def _check_element_size(element_size):
    h = np.broadcast_to(np.asarray(element_size, float), (2,)).copy() if element_size is not None else None
    if h is not None and (np.any(~np.isfinite(h)) or np.any(h <= 0)):
        raise InputError(pass_as(f"element_size must be > 0 mm, got {element_size!r}",
                                 f"--element-size must be > 0 mm, got "
                                 f"{' '.join(f'{v:g}' for v in np.atleast_1d(np.asarray(element_size, float)))}"))
    return h


def _is_3d(displacement, region) -> bool:
    """3D input: a result with a 3D mesh (duck typing: ``mesh.p`` of 3 rows), or a region of three intervals."""
    p = getattr(getattr(displacement, "mesh", None), "p", None)
    if p is not None and np.ndim(p) == 2:
        return np.shape(p)[0] == 3
    if region is None:
        return False
    try:
        flat = np.asarray(region, float).ravel()
    except (TypeError, ValueError):
        return False
    return flat.size == 6


def _check_region_3d(region):
    """(x0, x1, y0, y1, z0, z1) mm from ``(x0, x1, y0, y1, z0, z1)`` or ``((x0, x1), (y0, y1), (z0, z1))``."""
    try:
        v = tuple(float(a) for a in np.asarray(region, float).ravel())
    except (TypeError, ValueError):
        v = ()
    if len(v) != 6:
        raise InputError(f"a 3D region must be (x0, x1, y0, y1, z0, z1) mm, got {region!r}")
    if not all(np.isfinite(v)) or v[1] <= v[0] or v[3] <= v[2] or v[5] <= v[4]:
        raise InputError(f"a 3D region must be (x0, x1, y0, y1, z0, z1) mm with x0 < x1, y0 < y1 and z0 < z1, "
                         f"got {region!r}")
    return v


def _tensor_mesh_3d(bounds, h):
    from skfem import MeshHex1

    axes = [np.linspace(a, b, max(2, int(round((b - a) / hh))) + 1)
            for a, b, hh in zip(bounds[0::2], bounds[1::2], h)]
    return MeshHex1.init_tensor(*axes)


def _mesh_and_data_3d(displacement, region, element_size):
    """3D input: the hexahedral inversion mesh and the measured displacement at its nodes, interleaved
    (3 n_nodes,) [ux, uy, uz, ...] mm.  ``displacement``: a 3D registration result (``mesh`` a MeshHex1,
    ``displacement(points (n, 3)) -> (n, 3)``) or a callable with ``region``."""
    h = None
    if element_size is not None:
        try:
            h = np.broadcast_to(np.asarray(element_size, float), (3,)).copy()
        except ValueError:
            raise InputError(f"element_size must be a number or 3 numbers (mm) for 3D data, got {element_size!r}") \
                from None
        if np.any(~np.isfinite(h)) or np.any(h <= 0):
            raise InputError(f"element_size must be > 0 mm, got {element_size!r}")
    src = getattr(displacement, "mesh", None)
    if src is not None and callable(getattr(displacement, "displacement", None)):
        p = np.asarray(src.p, float)
        if region is None and h is None:
            mesh = src
        else:
            bounds = (_check_region_3d(region) if region is not None
                      else (p[0].min(), p[0].max(), p[1].min(), p[1].max(), p[2].min(), p[2].max()))
            if h is None:
                h = np.median(p[:, src.t].max(axis=1) - p[:, src.t].min(axis=1), axis=1)
            mesh = _tensor_mesh_3d(bounds, h)
        fun = displacement.displacement
    elif callable(displacement):
        if region is None:
            raise InputError("a 3D displacement callable needs region=(x0, x1, y0, y1, z0, z1) in mm")
        mesh = _tensor_mesh_3d(_check_region_3d(region), np.full(3, DEFAULT_ELEMENT_SIZE_3D) if h is None else h)
        fun = displacement
    else:
        raise InputError("displacement must be a registration result or a callable (n, 3) mm -> (n, 3) mm, "
                         f"got {type(displacement).__name__}")
    n = mesh.p.shape[1]
    try:
        v = np.asarray(fun(mesh.p.T.copy()), float)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a user's callable: report what it raised
        raise InputError(f"displacement callable failed on the mesh nodes: {type(exc).__name__}: {exc}") from None
    if v.shape != (n, 3):
        raise InputError(f"a 3D displacement must return shape ({n}, 3) for ({n}, 3) points, got {v.shape}")
    if not np.all(np.isfinite(v)):
        bad = counted(int((~np.all(np.isfinite(v), axis=1)).sum()), "node")
        raise InputError(f"the displacement has NaN/Inf at {bad} of the inversion mesh (region outside the measured "
                         "field?)")
    if mesh.t.shape[1] < 8:
        raise InputError(f"the inversion mesh has {mesh.t.shape[1]} element(s); need at least 2 x 2 x 2")
    return mesh, v.ravel().copy()


def _mesh_and_data(displacement, region, element_size):
    """(mesh, d, rule): the inversion mesh, the measured displacement at its nodes, interleaved (2 n_nodes,), and
    which mesh it is (a sentence); 3D input: :func:`_mesh_and_data_3d`.

    A registration result without ``region`` / ``element_size`` is inverted on its own mesh, unless adaptive
    refinement made that mesh (``refinement.base_size``): then on the tensor mesh of the unrefined element size
    over the mesh's bounding box.  Measured on 92 registered pairs (benchmarks/inversion.py, docs/inversion.md):
    as accurate as the refined mesh (81 against 79 in the 0.85-1.15 band, background CV <= 15 % on 85 against
    82) with 2-6 times fewer elements, so 5-20 times faster (the Laplace step is cubic in the elements)."""
    from .mesh import DEFAULT_ELEMENT_SIZE
    from .registration import RegistrationResult

    own = isinstance(element_size, str) and element_size == "registration"
    if _is_3d(displacement, region):
        if own and region is None:
            element_size = None             # a 3D result is inverted on its own mesh anyway
        mesh, d = _mesh_and_data_3d(displacement, region, element_size)
        return mesh, d, ("the registration's mesh" if region is None and element_size is None
                         else "a tensor mesh over the region")
    if own and (region is not None or not isinstance(displacement, RegistrationResult)):
        raise InputError('element_size="registration" takes a registration result and no region')
    h = None if own else _check_element_size(element_size)
    rule = None
    if isinstance(displacement, RegistrationResult):
        res = displacement
        base = getattr(getattr(res, "refinement", None), "base_size", None)
        if region is None and h is None and (base is None or own):
            rule = "the registration's mesh"
            mesh = res.mesh
            d = np.asarray(res.u, float).copy()
        else:
            p = res.mesh.p
            x0, x1, y0, y1 = (_check_region(region) if region is not None
                              else (p[0].min(), p[0].max(), p[1].min(), p[1].max()))
            if h is None:
                ext = p[:, res.mesh.t].max(axis=1) - p[:, res.mesh.t].min(axis=1)
                h = np.median(ext, axis=1)
                if base is not None:            # a refined registration: the size of the mesh it started from
                    h = np.asarray(base, float)
                    if region is None:
                        rule = (f"tensor mesh of the registration's unrefined element size {h[0]:.3g} x "
                                f"{h[1]:.3g} mm over its mesh's bounding box (the registration mesh was refined)")
            mesh = _tensor_mesh(x0, x1, y0, y1, h)
            v = res.displacement(mesh.p.T)
            if not np.all(np.isfinite(v)):
                raise InputError(f"region {((x0, x1), (y0, y1))} mm reaches outside the registration mesh "
                                 f"({counted(int((~np.isfinite(v[:, 0])).sum()), 'node')}); the mesh spans x "
                                 f"{p[0].min():.4g} to {p[0].max():.4g} mm, y {p[1].min():.4g} to {p[1].max():.4g} mm")
            d = np.empty(2 * mesh.p.shape[1])
            d[0::2], d[1::2] = v[:, 0], v[:, 1]
    elif callable(displacement):
        if region is None:
            raise InputError("a displacement callable needs region=((x0, x1), (y0, y1)) in mm")
        x0, x1, y0, y1 = _check_region(region)
        mesh = _tensor_mesh(x0, x1, y0, y1, np.asarray(DEFAULT_ELEMENT_SIZE, float) if h is None else h)
        try:
            v = np.asarray(displacement(mesh.p.T.copy()), float)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - a user's callable: report what it raised
            raise InputError(f"displacement callable failed on the mesh nodes: {type(exc).__name__}: {exc}") from None
        if v.shape != (mesh.p.shape[1], 2):
            raise InputError(f"displacement callable must return shape ({mesh.p.shape[1]}, 2) for "
                             f"({mesh.p.shape[1]}, 2) points, got {v.shape}")
        d = np.empty(2 * mesh.p.shape[1])
        d[0::2], d[1::2] = v[:, 0], v[:, 1]
    else:
        raise InputError("displacement must be a femreg.RegistrationResult or a callable (n, 2) mm -> (n, 2) mm, "
                         f"got {type(displacement).__name__}")
    if not np.all(np.isfinite(d)):
        raise InputError(f"the displacement has {int((~np.isfinite(d)).sum())} NaN/Inf values on the inversion "
                         "mesh (region outside the measured field?)")
    if mesh.t.shape[1] < 4:
        raise InputError(f"the inversion mesh has {mesh.t.shape[1]} element(s); need at least 2 x 2")
    if not inner_elements(mesh).any():     # the model tests and the region statistics read the inner elements
        lo, hi = mesh.p.min(axis=1), mesh.p.max(axis=1)
        raise InputError(f"the inversion mesh ({mesh.t.shape[1]} elements over x {lo[0]:.4g} to {hi[0]:.4g} mm, "
                         f"y {lo[1]:.4g} to {hi[1]:.4g} mm) has no element off its boundary; need at least 3 x 3: "
                         "a larger region (--region) or smaller elements (--element-size)")
    if rule is None:
        hh = mesh.p[:, mesh.t[2, 0]] - mesh.p[:, mesh.t[0, 0]]
        rule = f"tensor mesh of {abs(hh[0]):.3g} x {abs(hh[1]):.3g} mm over the region"
    return mesh, d, rule


def _element_strain(basis, d):
    """Mean strain [exx, eyy, exy] per element (n_el, 3) (3D: [exx, eyy, ezz, exy, exz, eyz], (n_el, 6)) and
    the RMS strain magnitude over the mesh (shear components counted twice)."""
    g = basis.interpolate(d).grad                       # (dim, dim, n_el, nq)
    w = basis.dx
    if g.shape[0] == 3:
        pairs = STRAIN_COMPONENTS_3D_INDEX
        comps = [0.5 * (g[i, j] + g[j, i]) for i, j in pairs]
        vol = w.sum(axis=1)
        el = np.stack([(c * w).sum(1) for c in comps], axis=1) / vol[:, None]
        sq = sum((1.0 if i == j else 2.0) * c ** 2 for (i, j), c in zip(pairs, comps))
        return el, float(np.sqrt(np.sum(sq * w) / np.sum(w)))
    exx, eyy, exy = g[0, 0], g[1, 1], 0.5 * (g[0, 1] + g[1, 0])
    area = w.sum(axis=1)
    el = np.stack([(exx * w).sum(1), (eyy * w).sum(1), (exy * w).sum(1)], axis=1) / area[:, None]
    rms = float(np.sqrt(np.sum((exx ** 2 + eyy ** 2 + 2 * exy ** 2) * w) / np.sum(w)))
    return el, rms


def _noise_weights(first) -> tuple:
    """(w_x, w_y, w_z) and a sentence: :data:`DEFAULT_WEIGHTS_3D` lowered by the misfit noise of ``first``, an
    inversion with those weights (:data:`WEIGHT_FLOOR_3D`)."""
    w0 = tuple(float(v) for v in DEFAULT_WEIGHTS_3D)
    r = (first.u_model - first.u_measured).reshape(-1, 3)
    inner = np.ones(len(r), bool)
    inner[first.mesh.boundary_nodes()] = False      # a fitted boundary absorbs part of its noise: interior only
    if inner.sum() < 1 or not np.all(np.isfinite(r[inner])):
        return w0, "misfit weights: the defaults (no interior nodes to measure the noise on)"
    sig2 = np.mean(r[inner] ** 2, axis=0)
    w = [w0[0]]
    for i in (1, 2):
        w.append(w0[i] if not sig2[i] > 0 else float(min(w0[i], max(WEIGHT_FLOOR_3D, w0[0] * sig2[0] / sig2[i]))))
    sig = ", ".join(f"{1e3 * np.sqrt(v):.3g}" for v in sig2)
    return tuple(w), (f"misfit weights {w[0]:g} / {w[1]:.3g} / {w[2]:.3g} (axial / lateral / elevational): the "
                      f"defaults {w0[0]:g} / {w0[1]:g} / {w0[2]:g}, lowered to w_x sigma_x^2 / sigma_i^2 (floor "
                      f"{WEIGHT_FLOOR_3D:g}), with the RMS misfit per component at the interior nodes of a first "
                      f"pass sigma = {sig} um")


def _weighted_median(v, w):
    o = np.argsort(v)
    c = np.cumsum(w[o])
    return float(v[o][np.searchsorted(c, 0.5 * c[-1])])


# ----------------------------------------------------------------------------------------------------------------
# model choice, checks, uncertainty, absolute scale
# ----------------------------------------------------------------------------------------------------------------
def _reference_elements(mesh, bounds) -> np.ndarray:
    """(n_el,) bool: the elements whose centre lies in the reference box ``bounds`` (x0, x1, y0, y1[, z0, z1]) mm;
    :class:`InputError` naming the mesh's span when none does or the box has the wrong number of intervals."""
    dim = mesh.p.shape[0]
    c = mesh.p[:, mesh.t].mean(axis=1)
    if len(bounds) != 2 * dim:
        raise InputError(f"the reference region {tuple(bounds)} mm has {len(bounds) // 2} intervals; the data have "
                         f"{dim} dimensions")
    sel = np.all([(c[k] >= bounds[2 * k]) & (c[k] <= bounds[2 * k + 1]) for k in range(dim)], axis=0)
    if not sel.any():
        span = ", ".join(f"{'xyz'[k]} {mesh.p[k].min():.4g} to {mesh.p[k].max():.4g}" for k in range(dim))
        raise InputError(f"the reference region {tuple(float(v) for v in bounds)} mm holds no element centre; the "
                         f"mesh spans {span} mm")
    return sel


def strain_ratio(el_strain, mesh) -> float:
    r"""Lateral-to-axial strain ratio :math:`r = -\varepsilon_{yy}/\varepsilon_{xx}` of the data
    (:func:`femreg.fields.lateral_ratio`: the median over the inner elements whose axial strain is at least half
    the median one).  NaN when fewer than 4 such elements."""
    return lateral_ratio(el_strain, mesh)


def _auto_model(ratio: float):
    r"""(model, lambda_bar, reduced volumetric integration, rule text) from the data's strain ratio r.

    Inverting :math:`r = \bar\lambda/(\bar\lambda+2)` gives :math:`\bar\lambda = 2r/(1-r)`: r = 1/2 is
    incompressible plane stress (:math:`\bar\lambda = 2`), :math:`r = \nu/(1-\nu)` plane strain (0.98 at
    :math:`\nu = 0.495`), 3D tissue under a finite probe lies between."""
    if not np.isfinite(ratio):
        return "plane-stress", 2.0, False, "auto: strain ratio undefined; plane stress assumed"
    if ratio <= AUTO_RATIO[0]:
        return "plane-stress", 2.0, False, f"auto: strain ratio {ratio:.3f} <= {AUTO_RATIO[0]:g}: plane stress"
    if ratio >= AUTO_RATIO[1]:
        return ("plane-strain", lambda_bar("plane-strain"), True,
                f"auto: strain ratio {ratio:.3f} >= {AUTO_RATIO[1]:g}: plane strain (nu {DEFAULT_POISSON:g})")
    lb = lambda_bar_from_ratio(ratio)
    return ("effective", lb, lb > 10.0,
            f"auto: strain ratio {ratio:.3f}: effective lambda_bar = 2 r / (1 - r) = {lb:.3g}")


def _lateral_shortfall(el_data, el_model, mesh, area_el, model: str):
    """(shortfall, reason): how much less the model's field expands laterally than the data's, and a reason string
    when that exceeds :data:`MODEL_RATIO_TOLERANCE` ('' otherwise).

    The inner elements (:func:`femreg.fields.inner_elements`) are split into four quadrants at their area-weighted
    median depth and lateral position; in each, the shortfall is ``1 - R_model / R_data`` with R = -mean(e_yy) /
    mean(e_xx) (area-weighted means of the element strains ``el_data``, ``el_model``), and the shortfall returned is
    the smallest of the four.  A lateral displacement biased by the registration (R_eps: lateral strain shrunk around an
    inclusion, raised inside) makes the data expand more than the model throughout the image, in every quadrant;
    noise in the lateral displacement moves the quadrants' ratios both ways (white lateral noise as large as the
    lateral strain: quadrant minima -0.02 to -0.29 over 24 fields), so it is not flagged.  One-sided: a model that
    expands more than the data is ``model="auto"``'s choice of plane strain for every ratio from
    :data:`AUTO_RATIO` [1] up, or noise.  The means, not medians of element ratios, so that a near-zero e_xx weighs
    nothing; NaN (no flag) with fewer than 4 elements in a quadrant."""
    inner = inner_elements(mesh)
    c = mesh.p[:, mesh.t].mean(axis=1)
    split = [c[k] < _weighted_median(c[k][inner], area_el[inner]) for k in (0, 1)]
    shorts = []
    for sx in (split[0], ~split[0]):
        for sy in (split[1], ~split[1]):
            sel = inner & sx & sy
            if sel.sum() < 4:
                return float("nan"), ""
            w = area_el[sel]
            r_d, r_m = (-np.sum(w * e[sel, 1]) / np.sum(w * e[sel, 0]) for e in (el_data, el_model))
            if not (np.isfinite(r_d) and np.isfinite(r_m) and r_d > 0):
                return float("nan"), ""
            shorts.append(1.0 - r_m / r_d)
    short = float(min(shorts))
    if short <= MODEL_RATIO_TOLERANCE:
        return short, ""
    return short, (f"the {model} model's own field expands laterally less than the data in every quadrant of the "
                   f"image (its lateral/axial strain ratio at least {100 * short:.0f} % short of the data's, "
                   f"tolerance {100 * MODEL_RATIO_TOLERANCE:.0f} %): the modulus fits the axial strain with a "
                   "lateral strain the data do not show, so the data are no displacement of this model (a lateral "
                   "displacement biased by the registration's regulariser, e.g. R_eps) and the contrast is not to "
                   "be trusted")


def _contradiction(mu, el_strain, mesh, area_el):
    """A reason string when a region's modulus contradicts its axial strain, else ''.

    Two tests on the inner elements (all elements when fewer than 8 are inner):

    - regions beyond a contrast: stiff = mu > :data:`CONTRAST_REGION` (median 1), soft = mu < 1 /
      :data:`CONTRAST_REGION`, background = within a factor 1.2 of 1.  A stiff region strains less than the
      background (|e_xx| smaller), a soft one more; the reverse by more than :data:`CONTRADICTION_MARGIN` is
      flagged.
    - any contrast (:func:`_ranked_contradiction`): the stiffer against the softer part of the image, which sees a
      small contrast on the wrong side of 1 that no element of it takes beyond :data:`CONTRAST_REGION`."""
    inner = inner_elements(mesh)
    ax = np.abs(el_strain[:, 0])
    bg = inner & (np.abs(np.log(mu)) < np.log(1.2))
    out = []
    if bg.sum() >= 2:
        e_bg = float(np.sum(area_el[bg] * ax[bg]) / np.sum(area_el[bg]))
        for name, sel, sign in (("stiff", inner & (mu > CONTRAST_REGION), 1),
                                ("soft", inner & (mu < 1 / CONTRAST_REGION), -1)):
            if sel.sum() < 2:
                continue
            e_r = float(np.sum(area_el[sel] * ax[sel]) / np.sum(area_el[sel]))
            if sign * (e_r / e_bg - 1.0) > CONTRADICTION_MARGIN:
                out.append(f"the {name} region ({counted(int(sel.sum()), 'element')}) strains "
                           f"{'more' if sign > 0 else 'less'} than the background (|e_xx| {e_r:.3g} vs {e_bg:.3g})")
    sel = inner if inner.sum() >= 8 else np.ones(mu.size, bool)
    ranked = _ranked_contradiction(mu, ax, sel, area_el)
    if ranked:
        out.append(ranked)
    layered = _layer_contradiction(mu, ax, mesh, sel, area_el)
    if layered:
        out.append(layered)
    return "; ".join(out)


def _layer_contradiction(mu, ax, mesh, sel, area_el) -> str:
    """The image's elements ``sel`` binned by depth (rows of about one element), each row's median log mu and
    median |e_xx| ``ax``: where the profile of the rows' modulus steps by at least :data:`LAYER_CONTRAST` between
    an upper and a lower part (the split of largest step, each side at least :data:`LAYER_MIN_AREA` of the area),
    a layer over another in series carries the same axial stress, so the stiffer part should strain less by about
    the modulus ratio.  When the strain's step is less than :data:`LAYER_EXPLAINED` of the modulus step (in log;
    negative: the wrong way), the layers are not in the data: '...', else ''.  A nearly incompressible plane-strain
    model with the measured displacement on every side admits such layers at equal strain (a pressure jump
    balances the axial traction, the measured sides take the lateral one), and a small error of the registered
    field's divergence selects them (a convex-probe pair: 2.6 x above 28 mm at equal strain).  An inclusion narrower
    than half the image does not move the rows' medians."""
    c = mesh.p[0, mesh.t].mean(axis=0)[sel]
    th, e, w = np.log(mu[sel]), ax[sel], area_el[sel]
    hx = float(np.median(np.ptp(mesh.p[0, mesh.t], axis=0)))
    lo, hi = float(c.min()), float(c.max())
    n_rows = int(np.clip(round((hi - lo) / max(hx, 1e-9)), 4, 60))
    row = np.minimum(((c - lo) / max(hi - lo, 1e-12) * n_rows).astype(int), n_rows - 1)
    m, s, a, z = (np.full(n_rows, np.nan) for _ in range(4))
    for k in range(n_rows):
        r = row == k
        if r.sum() >= 2:
            m[k], s[k], a[k], z[k] = np.median(th[r]), np.median(e[r]), w[r].sum(), np.mean(c[r])
    ok = np.isfinite(m) & (s > 0)
    m, s, a, z = m[ok], s[ok], a[ok], z[ok]
    if m.size < 4:
        return ""
    ca = np.cumsum(a) / a.sum()
    best, k_best = 0.0, -1
    for k in range(1, m.size):
        if ca[k - 1] < LAYER_MIN_AREA or 1.0 - ca[k - 1] < LAYER_MIN_AREA:
            continue
        step = np.average(m[:k], weights=a[:k]) - np.average(m[k:], weights=a[k:])
        if abs(step) > abs(best):
            best, k_best = step, k
    if k_best < 0 or abs(best) < np.log(LAYER_CONTRAST):
        return ""
    e_up, e_down = np.average(s[:k_best], weights=a[:k_best]), np.average(s[k_best:], weights=a[k_best:])
    explained = np.log(e_down / e_up) / best          # log(strain ratio below/above) / log(mu ratio above/below)
    if explained >= LAYER_EXPLAINED:
        return ""
    depth = 0.5 * (z[k_best - 1] + z[k_best])
    return (f"the rows above {depth:.3g} mm come out {np.exp(best):.3g} x as stiff as those below (row medians), "
            f"but strain {e_up / e_down:.3g} x as much (|e_xx| {e_up:.3g} vs {e_down:.3g}): layers in series share "
            f"one axial stress, so the stiffer should strain less by about the modulus ratio; the data do not show "
            f"these layers (explained {explained:.2f} of the step, at least {LAYER_EXPLAINED:g} needed)")


def _ranked_contradiction(mu, ax, sel, area_el) -> str:
    """The image's elements ``sel`` split in two at the middle of the 1-99 % range of log mu (area-weighted): with
    that range at least log :data:`RANKED_CONTRAST`, the stiffer part, whose mean mu is the larger, is flagged
    ('...') when its mean |e_xx| ``ax`` exceeds the softer part's by more than :data:`RANKED_MARGIN` (it should strain
    less); else ''.  Unlike the regions beyond :data:`CONTRAST_REGION`, this sees a contrast of a few percent.  The
    split sits between the image's extremes, so that where an inclusion stands out it is the inclusion that is
    tested, not the background's mild trends (the strain of a uniform body falls with depth under a probe)."""
    th, w = np.log(mu[sel]), area_el[sel]
    o = np.argsort(th)
    c = np.cumsum(w[o]) / np.sum(w)
    lo, hi = th[o][np.searchsorted(c, RANKED_RANGE[0])], th[o][min(np.searchsorted(c, RANKED_RANGE[1]), th.size - 1)]
    stiff = th > 0.5 * (lo + hi)
    soft = ~stiff
    if hi - lo < np.log(RANKED_CONTRAST) or stiff.sum() < 2 or soft.sum() < 2:
        return ""

    def mean(v, s):
        return float(np.sum(w[s] * v[s]) / np.sum(w[s]))

    contrast = mean(mu[sel], stiff) / mean(mu[sel], soft)
    e_stiff, e_soft = mean(ax[sel], stiff), mean(ax[sel], soft)
    if not e_stiff > (1.0 + RANKED_MARGIN) * e_soft:
        return ""
    return (f"its stiffer part ({int(stiff.sum())} of {stiff.size} elements, mean mu {contrast:.3g} x the softer "
            f"part's) strains {e_stiff / e_soft:.3g} x as much as the softer (|e_xx| {e_stiff:.3g} vs {e_soft:.3g}): "
            f"the strain puts the contrast on the other side of 1")


def _dof_target(area: float, n_el: int, h: float, dim: int, beta_method: str = "dof") -> float:
    r"""Number of parameters :math:`\gamma` the ``"dof"`` rules aim at (module docstring), at most half the elements.

    2D ``"dof"``: ``area / DOF_AREA * (DOF_ELEMENT_SIZE / h) ** DOF_EXPONENT`` (area mm^2, h the mean element size
    mm); ``"dof-area"``: ``area / DOF_AREA``.  3D (volume mm^3): ``area / DOF_AREA ** 1.5`` for both (one per the
    cube of 4.5 mm; not re-measured against the element size)."""
    if dim == 3:
        target = area / DOF_AREA ** 1.5
    elif beta_method == "dof-area":
        target = area / DOF_AREA
    else:
        target = area / DOF_AREA * (DOF_ELEMENT_SIZE / h) ** DOF_EXPONENT
    return float(min(target, 0.5 * n_el))


def _registered_sigma(h: float) -> float:
    """Factor on the Laplace std of a registered displacement inverted on elements of mean size h mm:
    REGISTERED_SIGMA x DOF_ELEMENT_SIZE / h, at least 1 (errors correlated over a fixed length, not a fixed
    number of elements)."""
    return float(max(REGISTERED_SIGMA * DOF_ELEMENT_SIZE / h, 1.0))


def _registered_factor(displacement, h: float, dim: int) -> float:
    """:func:`_registered_sigma` for the data ``displacement`` inverted on elements of mean size ``h`` mm: 1 unless
    it is a registration (module docstring: the registered field's errors are correlated over the registration's
    element size before adaptive refinement, which a refined mesh's smaller elements do not shorten)."""
    from .result import RegistrationResult

    if not isinstance(displacement, RegistrationResult):
        return 1.0
    base = getattr(getattr(displacement, "refinement", None), "base_size", None)
    h_reg = float(np.sqrt(np.prod(np.asarray(base, float)))) if base is not None and dim == 2 else h
    return _registered_sigma(h_reg)


def _data_hessian(fem, problem, theta):
    """Gauss-Newton Hessian of the misfit, H_d = S^T M S / s^2 (n_el, n_el), S = du/dtheta (:func:`_sensitivity`).

    With S = -K_II^{-1} B (B sparse, one element's DOFs per column): S^T M S = -B^T (K_II^{-1} M S), a second
    banded solve and a sparse product instead of the dense n_I x n_el x n_el product (n_I / bandwidth times the
    flops); column blocks of :data:`HESSIAN_COLUMNS` bound the memory to a few n_I x block arrays; symmetrised."""
    mu = np.exp(theta)
    u, lu = fem.solve(mu, problem.dirichlet)
    jac = _Jacobian(fem, mu, u, lu, dense_limit=0)
    MII = fem.M[fem.I][:, fem.I]
    BT = jac.B.T.tocsr()
    n = fem.n_el
    Hd = np.empty((n, n))
    for j in range(0, n, HESSIAN_COLUMNS):
        S = -lu.solve(jac.B[:, j:j + HESSIAN_COLUMNS].toarray())
        Hd[:, j:j + HESSIAN_COLUMNS] = -(BT @ lu.solve(MII @ S))
    Hd += Hd.T
    Hd *= 0.5 / problem.s2
    return Hd


def _effective_parameters(Hd, H):
    r""":math:`\gamma = \mathrm{tr}(H_d H^{-1})`, the number of parameters the data determine (MacKay 1992), and
    :math:`(H + \rho\,11^T/n)^{-1}`: H is singular along the constant mode (relative modulus), which the
    rank-one term fixes without changing :math:`\gamma` (:math:`H_d` is blind to it too)."""
    n = H.shape[0]
    rho = np.trace(H) / n
    C = _spd_inverse(H + rho / n * np.ones((n, n)))
    return float(np.sum(Hd * C)), C


def _spd_inverse(A) -> np.ndarray:
    """Inverse of a dense symmetric positive definite (n, n) matrix by Cholesky (LAPACK potrf + potri, n^3 flops,
    half of an LU inverse's); numpy's LU inverse where the Cholesky factorisation fails (not numerically positive
    definite)."""
    from scipy.linalg import lapack

    c, info = lapack.dpotrf(A, lower=False, clean=False)
    if info == 0:
        c, info = lapack.dpotri(c, lower=False, overwrite_c=True)
    if info != 0:
        return np.linalg.inv(A)
    iu = np.triu_indices_from(c, 1)      # potri fills the upper triangle only
    c.T[iu] = c[iu]
    return c


def _laplace(fem, reg, problem, theta, beta, n_data, Hd=None):
    r"""Per-element std of :math:`\log\mu` and the constrained mask from a Laplace approximation.

    Gauss-Newton Hessian of J: :math:`H = S^T M S / s^2 + \beta \nabla^2 R` with :math:`S = \partial u/\partial\theta
    = -K_{II}^{-1} [\mu_e K_e u]_I`.  J is read as a negative log-posterior at a temperature
    :math:`\tau = 2\phi/(n - \gamma)` (the misfit at the optimum equals its expected value for n data and
    :math:`\gamma = \mathrm{tr}(H_d H^{-1})` well-determined parameters), so :math:`\mathrm{Cov} = \tau H^{-1}`
    (MacKay, Neural Comput. 4 (1992) 415, eq. 2.22).  An element is constrained when
    its data information (diagonal of :math:`S^T M S / s^2`) is at least :data:`CONSTRAINED_INFO` of the median."""
    if Hd is None:      # else: the rule's, at the same theta
        Hd = _data_hessian(fem, problem, theta)
    H = Hd + beta * reg.hessian(theta)
    phi, _ = problem.misfit(theta)
    # J is blind to log mu + const (Dirichlet data everywhere): invert on the complement of the constant mode,
    # which the normalisation (median 1) fixes
    n = H.shape[0]
    rho = np.trace(H) / n
    try:
        C = _spd_inverse(H + rho / n * np.ones((n, n)))
        gamma = float(np.clip(np.sum(Hd * C), 0.0, n_data - 1.0))    # parameters the data determine
        tau = 2.0 * phi / max(n_data - gamma, 1.0)
        Cm = C.mean(axis=0)
        var = tau * (np.diag(C) - 2.0 * Cm + Cm.mean())    # diag of P C P, P = I - 1 1^T / n
    except np.linalg.LinAlgError:
        var = np.full(fem.n_el, np.nan)
    info = np.diag(Hd)
    constrained = info >= CONSTRAINED_INFO * np.median(info)
    std = np.sqrt(np.clip(var, 0, None))
    std[~constrained | ~np.isfinite(std)] = np.nan
    return std, constrained & np.isfinite(std)


def _regions(theta, reg, level: float, min_elements: int):
    """(labels (n_el,) int, candidates list of int, core (n_el,) bool): edge-connected components of equal quantised
    log mu (``round((theta - median) / level)``); a component of fewer than ``min_elements`` elements joins the
    neighbouring component of nearest mean log mu; candidates are all components but the largest (the reference);
    core marks the elements on their region's most common level (a merged speck, e.g. an element the disk's edge
    cuts, is not core and keeps its TV value in the refit)."""
    from scipy.sparse.csgraph import connected_components

    n = theta.size
    q = np.floor((theta - np.median(theta)) / level + 0.5)
    same = q[reg.a] == q[reg.b]
    graph = sp.coo_matrix((np.ones(int(same.sum())), (reg.a[same], reg.b[same])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    while True:
        sizes = np.bincount(labels)
        small = np.flatnonzero((sizes > 0) & (sizes < min_elements))
        if small.size == 0 or np.count_nonzero(sizes) <= 1:
            break
        means = np.bincount(labels, theta) / np.maximum(sizes, 1)
        k = small[np.argmin(sizes[small])]
        la, lb = labels[reg.a], labels[reg.b]
        nb = np.unique(np.r_[lb[la == k], la[lb == k]])
        nb = nb[nb != k]
        if nb.size == 0:
            break
        labels[labels == k] = nb[np.argmin(np.abs(means[nb] - means[k]))]
    _, labels = np.unique(labels, return_inverse=True)
    sizes = np.bincount(labels)
    ref = int(np.argmax(sizes))
    # a region's core: its elements on its most common level (not the specks merged into it)
    dominant = np.array([np.bincount((q[labels == k] - q.min()).astype(int)).argmax() + q.min()
                         for k in range(sizes.size)])
    return labels, [k for k in range(sizes.size) if k != ref], q == dominant[labels]


def _region_refit(fem, problem, reg, theta, n_data, sigma_factor, *, level, min_elements, sigma_max, max_shift,
                  cap="reject", mode="shift", maxiter=20, max_regions=None):
    """Region debias refit (:data:`TV_REFIT`): theta + P c, P the (n_el, k) indicators of the regions of
    :func:`_regions`, c minimising the misfit alone by Gauss-Newton with a backtracking line search.

    The marginal std of each shift, sqrt(tau [(P^T H_d P)^-1]_kk) x ``sigma_factor`` (H_d the Gauss-Newton Hessian
    of the misfit at ``theta``, tau = 2 phi / (n_data - k); :func:`_laplace`), selects the regions fitted (std <=
    ``sigma_max``); the fit is repeated without any region whose shift leaves +-``max_shift`` (``cap="reject"``),
    or such shifts are clipped (``"clip"``); more than ``max_regions`` candidate regions: nothing refitted
    (:data:`TV_REFIT_MAX_REGIONS`).  Returns (theta (n_el,), diagnostics dict: per candidate region
    its size, TV mean log mu, std, fitted shift and whether it was applied)."""
    labels, cand, core = _regions(theta, reg, level, min_elements)
    n = theta.size
    diag = {"regions": int(labels.max()) + 1, "candidates": [], "std_elements": np.full(n, np.nan),
            "too_many": max_regions is not None and len(cand) > max_regions}
    if not cand or diag["too_many"]:
        return theta, diag
    theta_tv = theta
    if mode != "shift":
        # piecewise constant on the cores of the refitted regions ("constant-all", "-fit": the reference's too)
        means = np.bincount(labels, theta * core) / np.maximum(np.bincount(labels, core.astype(float)), 1.0)
        flat = core & (np.isin(labels, cand) if mode == "constant" else True)
        theta = np.where(flat, means[labels], theta)
    P = sp.csr_matrix((core.astype(float), (np.arange(n), labels)),
                      shape=(n, int(labels.max()) + 1))[:, cand].tocsc()
    MII = fem.M[fem.I][:, fem.I]

    def linearise(th):
        mu = np.exp(th)
        u, lu = fem.solve(mu, problem.dirichlet)
        B = _Jacobian(fem, mu, u, lu, dense_limit=0).B
        SP = -lu.solve(np.asarray((B @ P).todense()))            # (n_I, k) du_I / dc
        r = (u - problem.d)[fem.I]
        Hr = SP.T @ (MII @ SP) / problem.s2
        g = SP.T @ (MII @ r) / problem.s2                       # d misfit / dc (interior residual only: u_B fixed)
        phi = 0.5 * float((u - problem.d) @ (fem.M @ (u - problem.d))) / problem.s2
        return phi, g, 0.5 * (Hr + Hr.T)

    phi0, _, H0 = linearise(theta)
    k = len(cand)
    tau = 2.0 * phi0 / max(n_data - k, 1.0)
    try:
        C = np.linalg.inv(H0)
        std = np.sqrt(np.clip(tau * np.diag(C), 0.0, None)) * sigma_factor
    except np.linalg.LinAlgError:
        std = np.full(k, np.inf)
    std[~np.isfinite(std)] = np.inf
    active = std <= sigma_max
    c, first = np.zeros(k), None
    for _ in range(k + 1):
        c = np.zeros(k)
        if not active.any():
            break
        idx = np.flatnonzero(active)
        phi = phi0
        for _ in range(maxiter):
            th = theta + P[:, idx] @ c[idx]
            phi, g, H = linearise(th)
            Ha = H[np.ix_(idx, idx)]
            try:
                step = -np.linalg.solve(Ha + 1e-12 * np.trace(Ha) * np.eye(idx.size), g[idx])
            except np.linalg.LinAlgError:
                break
            t = 1.0
            while t > 1e-3:
                trial = c.copy()
                trial[idx] += t * step
                trial = np.clip(trial, -2.0 * THETA_BOUND, 2.0 * THETA_BOUND)
                phi_t, _ = problem.misfit(np.clip(theta + P @ trial, -THETA_BOUND, THETA_BOUND))
                if phi_t < phi:
                    break
                t *= 0.5
            if t <= 1e-3:
                break
            c = trial
            if np.max(np.abs(t * step)) < 1e-4:
                break
        if first is None:
            first = c.copy()
        out = np.abs(c) > max_shift
        if cap == "clip" or not out.any():
            break
        active &= ~out
    fitted = c.copy() if first is None else first
    if cap == "clip":
        c = np.clip(c, -max_shift, max_shift)
    for j, lab in enumerate(cand):
        sel = (labels == lab) & core
        diag["candidates"].append({"elements": int(sel.sum()), "log_mu": float(np.mean(theta[sel])),
                                   "std": float(std[j]), "shift": float(fitted[j]), "applied": bool(active[j])})
    c[~active] = 0.0
    if not active.any():
        return theta_tv, diag
    out = theta + P @ c
    # the refitted regions' std: the Laplace approximation of the region model at its optimum (tau and the
    # registered-field factor as above), one value per region
    idx = np.flatnonzero(active)
    phi1, _, H1 = linearise(np.clip(out, -THETA_BOUND, THETA_BOUND))
    try:
        s1 = np.sqrt(np.clip(2.0 * phi1 / max(n_data - idx.size, 1.0)
                             * np.diag(np.linalg.inv(H1[np.ix_(idx, idx)])), 0.0, None)) * sigma_factor
    except np.linalg.LinAlgError:
        s1 = np.full(idx.size, np.nan)
    for j, sj in zip(idx, s1):
        diag["std_elements"][(labels == cand[j]) & core] = sj
    if mode != "shift":     # regions not refitted, and the specks, keep the TV values
        keep = np.isin(labels, np.asarray(cand)[~active]) | ~core
        if mode in ("constant", "constant-fit"):
            keep |= ~np.isin(labels, cand)      # the reference region too
        out = np.where(keep, theta_tv, out)
    return np.clip(out, -THETA_BOUND, THETA_BOUND), diag


def _constrained_blocks(fem, problem, theta, block: int = 256) -> np.ndarray:
    r"""(n_el,) bool, the constrained mask of :func:`_laplace` without its dense matrices: the data information
    :math:`\mathrm{diag}(S^T M S)/s^2` from column blocks of :math:`S = \partial u/\partial\theta` (one solve per
    element, ``block`` at a time)."""
    mu = np.exp(theta)
    u, lu = fem.solve(mu, problem.dirichlet)
    BI = _Jacobian(fem, mu, u, lu, dense_limit=0).B
    MII = fem.M[fem.I][:, fem.I]
    info = np.empty(fem.n_el)
    for j in range(0, fem.n_el, block):
        S = -lu.solve(BI[:, j:j + block].toarray())
        info[j:j + block] = np.sum(S * (MII @ S), axis=0) / problem.s2
    return info >= CONSTRAINED_INFO * np.median(info)


def _sensitivity(fem, mu, u, lu) -> np.ndarray:
    """Dense (n_I, n_el) du_I/dtheta = -K_II^{-1} [mu_e K_e u]_I."""
    return _Jacobian(fem, mu, u, lu, dense_limit=np.inf).dense


class _Jacobian:
    r""":math:`S = \partial u_I/\partial\theta = -K_{II}^{-1} B`, :math:`B = [\mu_e K_e u]_I` (sparse, n_I x n_el):
    dense while it has at most ``dense_limit`` entries, else as products (one solve with the factor ``lu`` each),
    never stored whole."""

    def __init__(self, fem, mu, u, lu, dense_limit):
        B = sp.csr_matrix((fem._data * u[fem._cols] * mu[fem._elem], (fem._rows, fem._elem)),
                          shape=(fem.basis.N, fem.n_el))
        self.B = B[fem.I].tocsc()
        self.lu = lu
        self.dense = -lu.solve(self.B.toarray()) if fem.I.size * fem.n_el <= dense_limit else None

    def matvec(self, v):
        return self.dense @ v if self.dense is not None else -self.lu.solve(self.B @ v)

    def rmatvec(self, w):
        return self.dense.T @ w if self.dense is not None else -(self.B.T @ self.lu.solve(w))

    def gram_trace(self, A, block: int = 256) -> float:
        """tr(S^T A S) for a sparse symmetric (n_I, n_I) A; without the dense S, ``block`` columns at a time."""
        if self.dense is not None:
            return float(np.sum(self.dense * (A @ self.dense)))
        out = 0.0
        for j in range(0, self.B.shape[1], block):
            S = -self.lu.solve(self.B[:, j:j + block].toarray())
            out += float(np.sum(S * (A @ S)))
        return out


#: The one-step inversion keeps du/dtheta dense while it has at most this many entries (n_I x n_el, 8 bytes each);
#: beyond, each Gauss-Newton system is solved by conjugate gradients with du/dtheta as products (two solves each).
ONE_STEP_DENSE_LIMIT = LAPLACE_DENSE_LIMIT
#: Conjugate-gradient iterations and relative residual of one Gauss-Newton step without the dense du/dtheta.
ONE_STEP_CG = (200, 1e-4)


def _one_step(fem, reg, d, theta0, beta, term, data_scale, *, maxiter=30, rtol=1e-5, trace=None):
    r"""One-step inversion: Gauss-Newton on :math:`\Psi(\theta) = \psi[u(\theta)]/c + \beta R(\theta)`, with
    :math:`\psi` the image term of eq:IR (fixed reference gradient, eq:wfnew; pixels in 2D, voxels in 3D) and
    u(θ) the model's displacement (boundary values d_B, the two-step inversion's), started from ``theta0``.  Each
    step solves :math:`(S^T H_\psi S/c + \beta\nabla^2 R)\,\Delta = -(S^T\nabla\psi/c + \beta\nabla R)` on the
    complement of the constant mode (S = du/dθ: dense up to :data:`ONE_STEP_DENSE_LIMIT` entries, else conjugate
    gradients, :data:`ONE_STEP_CG`) and backtracks on Ψ.  ``trace``: tr(S^T H_psi S) at ``theta0`` (scales the
    constant mode's term without a dense S).  Returns (theta, info)."""
    from scipy.sparse.linalg import LinearOperator, cg

    I = fem.I
    Hpsi = sp.csr_matrix(term.hessian())
    HII = Hpsi[I][:, I]
    theta = theta0.copy()
    n = theta.size

    def value(th):
        u, lu = fem.solve(np.exp(th), d)
        return term.energy(u) / data_scale + beta * reg(th)[0], u, lu

    J, u, lu = value(theta)
    J0 = J
    history = [J]
    ok, msg, it, n_cg = True, "converged", 0, 0
    for it in range(1, maxiter + 1):
        mu = np.exp(theta)
        S = _Jacobian(fem, mu, u, lu, ONE_STEP_DENSE_LIMIT)
        g = S.rmatvec(term.gradient(u)[I]) / data_scale + beta * reg(theta)[1]
        if S.dense is not None:
            H = S.dense.T @ (HII @ S.dense) / data_scale + beta * reg.hessian(theta)
            rho = np.trace(H) / n
            step = -np.linalg.solve(H + rho / n * np.ones((n, n)) + 1e-10 * rho * np.eye(n), g)
        else:
            HR = reg.hessian(theta, sparse=True)
            rho = ((S.gram_trace(HII) if trace is None else trace) / data_scale + beta * HR.diagonal().sum()) / n

            def apply(v, S=S, HR=HR, rho=rho):
                return (S.rmatvec(HII @ S.matvec(v)) / data_scale + beta * (HR @ v) + rho / n * v.sum()
                        + 1e-10 * rho * v)

            count = []
            step, _ = cg(LinearOperator((n, n), matvec=apply, dtype=float), -g, rtol=ONE_STEP_CG[1],
                         maxiter=ONE_STEP_CG[0], callback=lambda xk: count.append(1))
            n_cg += len(count)
        step -= step.mean()
        t = 1.0
        while t > 1e-3:
            cand = np.clip(theta + t * step, -THETA_BOUND, THETA_BOUND)
            Jc, uc, luc = value(cand)
            if Jc < J:
                break
            t *= 0.5
        else:
            msg = "no descent along the Gauss-Newton step"
            break
        drop = (J - Jc) / max(abs(J), 1e-300)
        theta, J, u, lu = cand, Jc, uc, luc
        history.append(J)
        if drop < rtol:
            break
    else:
        ok, msg = False, f"not converged in {maxiter} Gauss-Newton iterations"
    return theta, {"success": ok, "message": msg, "nit": it, "objective_start": J0, "objective": J,
                   "history": history, "cg_iterations": n_cg}


def _check_images(displacement, region, reference_image, moving_image):
    """The registered pair of the one-step inversion as float64 arrays, checked against ``displacement``: a 2D
    :class:`femreg.RegistrationResult` and two images of its grid, or a :class:`femreg.VolumeResult` and two
    volumes of its grid."""
    from .image import validate_image
    from .registration import RegistrationResult
    from .volume_result import VolumeResult
    from .voxels import validate_volume

    if reference_image is None or moving_image is None:
        raise InputError("the one-step inversion needs both reference_image and moving_image")
    three = _is_3d(displacement, region)
    kind = VolumeResult if three else RegistrationResult
    if not isinstance(displacement, kind):
        raise InputError(f"the one-step inversion needs the pair's {kind.__name__} as displacement, got "
                         f"{type(displacement).__name__}")
    check = validate_volume if three else validate_image
    images = (check(reference_image, "reference image" if not three else "reference volume"),
              check(moving_image, "moving image" if not three else "moving volume"))
    if images[0].shape != tuple(displacement.shape) or images[1].shape != images[0].shape:
        swapped = ("; their axes are the grid's exchanged: frames stored lines first, transpose them ("
                   + pass_as("CLI: --transpose", "--transpose") + ")"
                   if not three and images[0].shape == tuple(displacement.shape)[::-1] else "")
        raise InputError(f"{'volumes' if three else 'images'} {images[0].shape} / {images[1].shape} do not match "
                         f"the registration grid {tuple(displacement.shape)}{swapped}")
    return images


def _image_term(src, mesh, images):
    """The image term of eq:IR (fixed reference gradient, eq:wfnew) of the registered pair ``images`` on the
    inversion mesh, each image normalised (minus its mean, over its spread) as the registration does: pixel quadrature
    (:func:`femreg.registration.image_term`) in 2D, voxels (:class:`femreg.voxels.VoxelSSDTerm`) in 3D."""
    from .image import SplineImage, normalize_pair

    r1, r2, _ = normalize_pair(*images)
    if mesh.p.shape[0] == 3:
        from .voxels import SplineVolume, VoxelGrid, VoxelSSDTerm

        return VoxelSSDTerm(VoxelGrid(mesh, src.shape, src.spacing, src.origin),
                            SplineVolume(r1, src.spacing, src.origin),
                            SplineVolume(r2, src.spacing, src.origin, keep_data=False))
    from .registration import image_term

    return image_term(SplineImage(r1, src.spacing, src.origin), SplineImage(r2, src.spacing, src.origin), mesh,
                      src.shape, src.spacing, src.origin)


def _check_reference(reference):
    try:
        region, value = reference
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"reference must be (((x0, x1), (y0, y1)), E_kPa), got {reference!r}") from None
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"the reference Young's modulus must be > 0 kPa, got {value!r}")
    try:
        n = np.asarray(region, float).size
    except (TypeError, ValueError):
        n = 0
    if n == 6:
        return _check_region_3d(region), value
    return _check_region(region), value


# ----------------------------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------------------------
@single_blas_thread
def invert(displacement, *, model: str = "auto", region=None, element_size=None, beta=None,
           regularization: str = "tv", weights=None, poisson: float | None = None,
           maxiter: int = 400, gtol: float = 1e-7, beta_grid=None, progress: bool = False, reference=None,
           uncertainty: bool = True, beta_method: str = "dof", boundary: str | None = None,
           reference_image=None, moving_image=None) -> "InversionResult":
    r"""Relative shear-modulus image from a measured displacement (eq:cEq / eq:meq inverse problem).

    Parameters
    ----------
    displacement : RegistrationResult or callable
        The measured field: a :class:`femreg.RegistrationResult` (inverted on its own mesh, or on a structured
        mesh of ``element_size`` over ``region`` / its mesh's bounding box), or a callable ``(n, 2) [x, y] mm ->
        (n, 2) [ux, uy] mm`` together with ``region``.  3D: a result with a hexahedral ``mesh`` and
        ``displacement(points (n, 3)) -> (n, 3)``, or a callable ``(n, 3) [x, y, z] -> (n, 3) [ux, uy, uz]`` mm
        with ``region=(x0, x1, y0, y1, z0, z1)``; inverted with ``model="3d"`` (module docstring).
    model : {"auto", "plane-stress", "plane-strain", "3d"}
        :math:`\bar\lambda = 2\nu/(1-\nu)` (plane stress; 2, incompressible, by default) or :math:`2\nu/(1-2\nu)` (plane strain, reduced
        integration of the volumetric term).  ``"auto"`` (default) follows the data: under uniaxial stress the
        2D model strains laterally by :math:`r = \bar\lambda/(\bar\lambda+2)` of the axial strain (1/2 in
        incompressible plane stress, :math:`\nu/(1-\nu) \approx 0.98` in plane strain; tissue imaged in a
        3D body lies between); the measured median ratio :func:`strain_ratio` picks plane stress
        (:math:`r \le` 0.55), plane strain (:math:`r \ge` 0.9) or the effective :math:`\bar\lambda = 2r/(1-r)`
        between them (``model="effective"`` in the result; ``model_rule`` says why).  3D data take ``"3d"``
        (``"auto"`` picks it): :math:`\bar\lambda = 2\nu/(1-2\nu)`, ``poisson`` default 0.495.  An explicit
        model whose ratio differs from the data's by more than :data:`RATIO_TOLERANCE` is flagged (``success=False``).
    region : ((x0, x1), (y0, y1)) mm, optional (3D: (x0, x1, y0, y1, z0, z1))
        Region to invert (a rectangle); required with a callable.
    element_size : float or (2,) mm, optional
        Element size of the structured inversion mesh (default: the registration mesh itself, or, for a
        registration whose mesh adaptive refinement made, the tensor mesh of its unrefined element size
        ``refinement.base_size`` over the mesh's bounding box (``mesh_rule`` in the result says which;
        ``"registration"``: the registration's own mesh, refined or not); or
        :data:`femreg.mesh.DEFAULT_ELEMENT_SIZE` for a callable; 3D: (3,), default
        :data:`DEFAULT_ELEMENT_SIZE_3D`).
    beta : float >= 0, optional
        :math:`\beta`, weight of the regulariser; None = the rule of the module docstring (sweep of ``beta_grid``,
        default :data:`BETA_GRID`; ``beta_method`` "dof" (default), "dof-area" (the former
        default: the target per area alone), "growth" or "l-curve").
    regularization : {"tv", "tikhonov"}
        Total variation (default: sharp inclusion edges) or Tikhonov (smooth) of :math:`\log\mu`.
    weights : (w_x, w_y) or, for 3D data, (w_x, w_y, w_z), optional
        Misfit weights of the axial and lateral (and elevational) components (default :data:`DEFAULT_WEIGHTS`;
        3D: two weights mean (w_x, w_y, w_y); None for 3D data: :data:`DEFAULT_WEIGHTS_3D` lowered by the data's
        noise measured in a first inversion, module docstring).
    poisson : float, optional
        :math:`\nu` (plane strain: in (-1, 0.5), default 0.495; plane stress: in (-1, 0.5], default 0.5).
    boundary : {"measured", "axial-sides", "free-sides", "fitted"}, optional
        Boundary conditions of the forward model (:data:`BOUNDARIES`): the measured displacement on the whole
        boundary (None for 2D data); ``"fitted"``: the lateral and elevational boundary values are fitted by the
        misfit beside the modulus (None for 3D data with :data:`FITTED_MIN_ELEMENTS` elements across every axis,
        module docstring).
    maxiter, gtol
        L-BFGS-B iteration limit and projected-gradient tolerance per solve.
    progress : bool
        tqdm bar over the beta values of the sweep, the current beta and its optimiser iteration beside it.
    reference : (((x0, x1), (y0, y1)), E_kPa), optional
        A region (mm) of known Young's modulus E (kPa), e.g. a phantom's documented background: the result
        then carries ``shear_modulus_kpa`` = mu scaled so that its area-weighted mean over the region's elements
        (centres inside) is E/3, and ``youngs_modulus_kpa`` = 3 ``shear_modulus_kpa`` (incompressible).
    reference_image, moving_image : (n_axial, n_lateral) arrays, or (n_x, n_y, n_z) volumes, optional
        The registered pair (``displacement`` must then be its :class:`femreg.RegistrationResult`, or for volumes
        its :class:`femreg.VolumeResult`): after the two-step inversion, a one-step inversion minimises the image
        term of eq:IR (pixels, or voxels) over log mu with the model's displacement (:func:`_one_step`; Gokhale et
        al., Inverse Probl. 20 (2004) 1531, doi:10.1088/0266-5611/20/5/013), started from the two-step result, with
        the same beta and boundary values (3D: the fitted ones); the image term is scaled so that its Gauss-Newton
        information on log mu has the trace of the displacement misfit's.  ``one_step`` in the result records the
        image term and the objective before and after, the iterations and the seconds.  3D with
        ``weights=None``: the noise-measuring first pass runs without the images.
    uncertainty : bool
        Compute ``uncertainty`` (per-element std of log mu, Laplace approximation, NaN where not
        ``constrained``; for a registered displacement times :func:`_registered_sigma`, :data:`REGISTERED_SIGMA` x
        :data:`DOF_ELEMENT_SIZE` / h); costs one dense Hessian of size n_el.  Calibrated on inclusions in a
        uniform background (55-80 % of the true log mu within +-1 sigma on registered disks); a 2D image of more
        than :data:`CALIBRATION_MAX_REGIONS` regions (tissue whose stiffness varies everywhere, where the std
        alone held 23 % of the true log mu) returns ``uncertainty_calibrated=False``, a note in ``notes``, and the
        std widened by the bias term of :data:`UNCALIBRATED_SPREAD` (62 % on such registered tissue).  A calibrated
        2D TV std is widened to at least the background's own scatter (:data:`SCATTER_FLOOR`, factor max(1, robust
        spread of log mu over the largest region / RMS of its Laplace std), ``uncertainty_scale`` in the result):
        never narrowed, the modulus unchanged.

    Returns
    -------
    InversionResult
        ``mu`` (n_el,) element values with median 1, ``shear_modulus(points)``, ``success``, ``message``,
        ``flags`` (list of reasons), ``uncertainty_calibrated``, ``unsupported_area`` and ``notes`` (remarks
        that are no flag),
        convergence ``history``.  ``success=False`` with the reasons when the
        optimisation fails, :math:`\beta` sits on the edge of its grid (the large edge only for an image that is
        not flat), :math:`|\log\mu|` reaches its bound,
        the model contradicts the data's strain ratio, the misfit stays above :data:`MISFIT_LIMIT` (the noise level
        of registered fields), or a stiff (soft) region, or the stiffer (softer) part of an image of any contrast
        (:func:`_contradiction`), strains more (less) than the rest, or a 2D TV image without the region refit
        has more than :data:`UNSUPPORTED_AREA` of its area in regions the axial strain does not support
        (``unsupported_area``, :func:`_unsupported_regions`; with the refit, or less, a note).

    Raises
    ------
    InputError
        Naming the bad argument (unknown model, bad region, NaN displacement, a field without deformation, ...).
    """
    t_all = time.perf_counter()
    three = _is_3d(displacement, region)
    auto_boundary = boundary is None and three       # resolved on the mesh (FITTED_MIN_ELEMENTS)
    if boundary is None:
        boundary = "measured"
    if weights is None and not three:
        weights = DEFAULT_WEIGHTS
    if weights is None:
        # 3D: the component weights from the noise of a first pass (WEIGHT_FLOOR_3D, module docstring)
        common = dict(model=model, region=region, element_size=element_size, beta=beta,
                      regularization=regularization, poisson=poisson, maxiter=maxiter, gtol=gtol,
                      beta_grid=beta_grid, progress=progress, beta_method=beta_method,
                      boundary=None if auto_boundary else boundary)
        images = dict(reference_image=reference_image, moving_image=moving_image)
        if reference_image is not None or moving_image is not None:
            _check_images(displacement, region, reference_image, moving_image)     # before the first pass
        # the first pass only measures the noise: the one-step inversion (images) runs in the second
        first = invert(displacement, weights=DEFAULT_WEIGHTS_3D, uncertainty=False, **common)
        w, why = _noise_weights(first)
        if (w == tuple(DEFAULT_WEIGHTS_3D) and not uncertainty and reference is None
                and reference_image is None):
            res = first
        else:
            res = invert(displacement, weights=w, uncertainty=uncertainty, reference=reference, **common, **images)
        res.model_rule += "; " + why
        res.timings["first_pass"] = first.timings["total"]
        res.timings["total"] = time.perf_counter() - t_all
        return res
    if model == "auto":
        if poisson is not None and not _is_3d(displacement, region):
            raise InputError(pass_as("poisson applies to model='plane-strain' only (model='auto' measures lambda_bar)",
                                     "--poisson applies to --model plane-strain only (--model auto measures the "
                                     "material's lambda-bar from the data)"))
    else:
        lb = lambda_bar(model, poisson)
    ref = None if reference is None else _check_reference(reference)
    images = None
    if reference_image is not None or moving_image is not None:
        images = _check_images(displacement, region, reference_image, moving_image)
    if regularization not in ("tv", "tikhonov"):
        raise InputError(f"regularization must be 'tv' or 'tikhonov', got {regularization!r}")
    try:
        w = np.asarray(weights, float).ravel()
        if w.size not in (2, 3):
            raise ValueError
    except (TypeError, ValueError):
        raise InputError(f"weights must be two numbers (axial, lateral), or three (axial, lateral, elevational) "
                         f"for 3D data, got {weights!r}") from None
    if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise InputError(f"weights must be >= 0 and not both 0, got {weights!r}")
    if beta is not None:
        try:
            beta = float(beta)
        except (TypeError, ValueError):
            raise InputError(f"beta must be a number >= 0 or None, got {beta!r}") from None
        if not (np.isfinite(beta) and beta >= 0):
            raise InputError(pass_as(f"beta must be a finite number >= 0, got {beta!r}",
                                     f"--beta must be a finite number >= 0, got {beta:g}"))
    grid = BETA_GRID if beta_grid is None else tuple(sorted((float(b) for b in beta_grid), reverse=True))
    if not grid or not all(np.isfinite(b) and b >= 0 for b in grid):
        raise InputError(f"beta_grid must hold finite numbers >= 0, got {beta_grid!r}")
    if boundary not in BOUNDARIES:
        raise InputError(f"boundary must be one of {BOUNDARIES}, got {boundary!r}")
    if beta_method not in BETA_METHODS:
        raise InputError(f"beta_method must be one of {BETA_METHODS}, got {beta_method!r}")
    if int(maxiter) < 1 or not (np.isfinite(gtol) and gtol > 0):
        raise InputError(pass_as(f"need maxiter >= 1 and gtol > 0, got maxiter={maxiter}, gtol={gtol}",
                                 f"--maxiter must be an integer >= 1, got {maxiter}"))

    mesh, d, mesh_rule = _mesh_and_data(displacement, region, element_size)
    dim = mesh.p.shape[0]
    if dim == 2 and (model == "3d" or w.size != 2):
        raise InputError("2D data take a 2D model (model 'auto', 'plane-stress' or 'plane-strain') and two "
                         f"weights, got model={model!r}, weights={weights!r}")
    if dim == 3:
        if model not in ("auto", "3d"):
            raise InputError(f"3D data take model='3d' (or 'auto'), got model={model!r}")
        w = np.r_[w, w[1]] if w.size == 2 else w     # (w_x, w_y) -> (w_x, w_y, w_y)
    if ref is not None:
        _reference_elements(mesh, ref[0])           # a box that misses the mesh: before the optimisation
    t = time.perf_counter()
    from skfem import Basis, ElementVector

    el_strain, eps_rms = _element_strain(Basis(mesh, ElementVector(_elements(mesh)[0]), intorder=2), d)
    if not (eps_rms > 1e-12):
        raise InputError("the displacement has no deformation over the region (RMS strain "
                         f"{eps_rms:.3g}): the modulus cannot be identified")
    ratio = strain_ratio(el_strain, mesh)
    flags = []
    slides = [v for v in getattr(getattr(displacement, "refinement", None), "slides", ())
              if mesh.p[1].min() < v < mesh.p[1].max()]      # the slips inside the inverted region
    if slides:
        # a frictionless slip is no continuum: the model would put the slip's shear into the modulus
        flags.append(f"the registration found tissue sliding along the beam near y = "
                     f"{', '.join(f'{v:.1f}' for v in slides)} mm: a bonded elastic model does not hold across a "
                     "slip; invert a region on one side of it (region=)")
    if dim == 3:
        # 3D elasticity is the model of 3D data itself: no lambda_bar to measure, no model to check
        lb = lambda_bar("3d", poisson)
        reduced = True
        model_rule = ("auto: 3D data: 3D" if model == "auto" else "given: 3D") + \
            f" nearly incompressible elasticity (nu {DEFAULT_POISSON if poisson is None else poisson:g})"
        model = "3d"
        if auto_boundary:
            n_across = min(np.unique(np.round(mesh.p[a], 9)).size - 1 for a in range(3))
            boundary = BOUNDARY_3D if n_across >= FITTED_MIN_ELEMENTS else "measured"
            model_rule += (f"; boundary values {'fitted' if boundary == 'fitted' else 'measured'} ("
                           f"{n_across} elements across the thinnest axis, fitted from {FITTED_MIN_ELEMENTS})")
    elif model == "auto":
        model, lb, reduced, model_rule = _auto_model(ratio)
        # below plane stress (or above plane strain) no incompressible 2D model fits the lateral strain, e.g. a
        # lateral displacement that is noise
        if np.isfinite(ratio) and abs(ratio - model_ratio(lb)) > AUTO_RATIO_TOLERANCE:
            flags.append(f"the data's lateral/axial strain ratio {ratio:.2f} is outside what any model gives "
                         f"({model_ratio(2.0):.2f} plane stress to {model_ratio(lambda_bar('plane-strain')):.2f} "
                         "plane strain): out-of-plane motion or an untrustworthy lateral displacement, which no 2D "
                         "model describes")
    else:
        reduced = model == "plane-strain"
        model_rule = "given"
        if np.isfinite(ratio) and abs(ratio - model_ratio(lb)) > RATIO_TOLERANCE:
            flags.append(f"the data's lateral/axial strain ratio {ratio:.2f} contradicts the {model} model "
                         f"({model_ratio(lb):.2f}, tolerance {RATIO_TOLERANCE:g}); try "
                         + pass_as("model='auto'", "--model auto"))
    fem = _Model(mesh, lb, reduced_volumetric=reduced, weights=w, boundary=boundary)
    ext = mesh.p[:, mesh.t].max(axis=1) - mesh.p[:, mesh.t].min(axis=1)
    if dim == 2:
        h = float(np.sqrt(np.mean(ext[0] * ext[1])))
    else:
        h = float(np.cbrt(np.mean(ext[0] * ext[1] * ext[2])))
    s2 = fem.area * (eps_rms * h) ** 2
    reg = _Regularizer(mesh, regularization, h, fem.area)
    problem = _Problem(fem, reg, d, s2, fit_boundary=boundary == "fitted")
    t_setup = time.perf_counter() - t

    bar = _SweepBar(1 if beta is not None else len(grid), maxiter) if progress else None
    theta = np.zeros(fem.n_el)
    sweep = []
    target_dof = _dof_target(fem.area, fem.n_el, h, dim, beta_method)
    hd_cache = {}
    t = time.perf_counter()
    try:
        betas = [beta] if beta is not None else list(grid)
        runs = []
        above = None        # a solve above the grid kept out by the up-steps: the bracket's larger beta (DOF_STEP_BACK)
        chosen = None
        for b in betas:
            if bar is not None:
                bar.start(b)
            theta_b, info = _optimise(problem, theta, b, maxiter=maxiter, gtol=gtol, progress=bar)
            if bar is not None:
                bar.done()
            if np.any(np.abs(theta_b) >= THETA_BOUND - 1e-6):
                info = dict(info, success=False, message=f"log-modulus reached its bound |log mu| = "
                                                         f"{THETA_BOUND:g} ({info['message']})")
            phi, _ = problem.misfit(theta_b)
            R, _ = reg(theta_b)
            sweep.append({"beta": b, "misfit": phi, "regularizer": R, "nit": info["nit"],
                          "success": info["success"], "message": info["message"]})
            if runs and beta is None and not info["success"]:
                chosen = runs[-1]        # no convergence at this beta: the previous one is the last reliable
                sweep[-1]["stop"] = "not converged"
                break
            if beta is None and beta_method in ("dof", "dof-area"):
                Hd_b = _data_hessian(fem, problem, theta_b)
                hd_cache[b] = Hd_b
                gam, _ = _effective_parameters(Hd_b, Hd_b + b * reg.hessian(theta_b))
                sweep[-1]["gamma"] = gam
                if gam >= target_dof:       # gamma grows as beta falls: the nearer (in log) of the two betas
                    prev = sweep[-2]["gamma"] if runs else np.nan
                    if runs and abs(np.log(prev / target_dof)) < abs(np.log(gam / target_dof)):
                        chosen = runs[-1]
                    else:
                        chosen = (b, theta_b.copy(), info, phi, R)
                    break
            elif runs and beta is None:
                b0, _, _, phi0, R0 = runs[-1]
                slope = (np.log(max(R, 1e-300) / max(R0, 1e-300))
                         / max(np.log(max(phi0, 1e-300) / max(phi, 1e-300)), 1e-12))
                growth = np.log(max(R, 1e-300) / max(R0, 1e-300)) / max(np.log(max(b0, 1e-300) / max(b, 1e-300)),
                                                                       1e-12)
                sweep[-1]["slope"] = float(slope)
                sweep[-1]["growth"] = float(growth)
                if (slope > LCURVE_SLOPE) if beta_method == "l-curve" else (growth > GROWTH_RATE):
                    chosen = runs[-1]
                    break
            runs.append((b, theta_b.copy(), info, phi, R))
            theta = theta_b
            if not info["success"] and "failed" in info["message"]:
                break
        if (beta is None and beta_grid is None and beta_method in ("dof", "dof-area") and chosen is not None
                and chosen[0] == grid[0]
                and len(sweep) == 1 and sweep[0]["gamma"] > target_dof):
            # more parameters than the target already at the largest beta of the default grid (fine meshes, in
            # vivo noise): go up by half decades, DOF_UP_STEPS at most; the grid's edge is then the largest of these
            g_prev, up = sweep[0]["gamma"], []
            for k in range(1, DOF_UP_STEPS + 1):
                b = grid[0] * 10.0 ** (0.5 * k)
                up.insert(0, b)
                if bar is not None:
                    bar.extend()
                    bar.start(b)
                theta_b, info = _optimise(problem, chosen[1], b, maxiter=maxiter, gtol=gtol, progress=bar)
                if bar is not None:
                    bar.done()
                phi, _ = problem.misfit(theta_b)
                R, _ = reg(theta_b)
                Hd_b = _data_hessian(fem, problem, theta_b)
                hd_cache[b] = Hd_b
                gam, _ = _effective_parameters(Hd_b, Hd_b + b * reg.hessian(theta_b))
                sweep.insert(0, {"beta": b, "misfit": phi, "regularizer": R, "nit": info["nit"],
                                 "success": info["success"], "message": info["message"], "gamma": gam})
                if not info["success"]:
                    break
                cand = (b, theta_b.copy(), info, phi, R)
                if gam <= target_dof:
                    if abs(np.log(gam / target_dof)) < abs(np.log(g_prev / target_dof)):
                        chosen = cand
                    else:
                        above = cand
                    break
                chosen, g_prev = cand, gam
            grid = tuple(up) + tuple(grid)
    finally:
        if bar is not None:
            bar.close()
    name = {"l-curve": "L-curve", "growth": "R-growth", "dof": "effective parameters",
            "dof-area": "effective parameters per area"}[beta_method]
    target_text = (f"area / {DOF_AREA:g} mm^2" if beta_method == "dof-area" or dim == 3 else
                   f"area / {DOF_AREA:g} mm^2 x ({DOF_ELEMENT_SIZE:g} mm / h {h:.2g} mm)^{DOF_EXPONENT:g}")
    if beta is not None:
        rule = "given"
    elif chosen is not None and beta_method in ("dof", "dof-area") and not sweep[-1].get("stop"):
        g_chosen = next(e["gamma"] for e in sweep if e["beta"] == chosen[0])
        rule = (f"{name}: the beta of {[f'{x:.3g}' for x in grid]} whose gamma = tr(H_d H^-1) is "
                f"nearest {target_text} = {target_dof:.3g} (gamma {g_chosen:.3g})")
    elif chosen is not None and sweep[-1].get("stop"):
        rule = (f"{name}: last beta of {[f'{x:.3g}' for x in grid]} before a solve that did not converge "
                f"(beta {sweep[-1]['beta']:.3g})")
    elif chosen is not None and beta_method == "l-curve":
        rule = (f"L-curve: last beta of {[f'{x:.3g}' for x in grid]} before the slope d log R / -d log misfit "
                f"exceeds {LCURVE_SLOPE:g}")
    elif chosen is not None:
        rule = (f"R-growth: last beta of {[f'{x:.3g}' for x in grid]} before the regulariser grows as "
                f"d log R / -d log beta > {GROWTH_RATE:g}")
    elif beta_method in ("dof", "dof-area"):
        rule = (f"{name}: gamma stays below {target_text} = {target_dof:.3g} on "
                f"{[f'{x:.3g}' for x in grid]}; smallest beta reached")
    else:
        rule = f"{name}: no corner on {[f'{x:.3g}' for x in grid]}; smallest beta reached"
    if chosen is None:
        chosen = runs[-1]
    def region_refit(theta_start):
        """:func:`_region_refit` of ``theta_start`` with the module's refit settings (TV_REFIT and its kin)."""
        return _region_refit(fem, problem, reg, theta_start, fem.I.size, _registered_factor(displacement, h, dim),
                             level=TV_REFIT, min_elements=TV_REFIT_MIN_ELEMENTS, sigma_max=TV_REFIT_SIGMA,
                             max_shift=TV_REFIT_MAX_SHIFT, cap=TV_REFIT_CAP, mode=TV_REFIT_MODE,
                             max_regions=TV_REFIT_MAX_REGIONS)

    def debiased(cand):
        """The debiased TV (reweighting, Bregman, region refit) of one sweep result ``cand`` = (beta, theta, info,
        phi, R): (theta, info, phi, R, theta_part, theta_tv, refit_std, refit_skipped, rule text)."""
        b, theta, info, phi, R = cand
        if info.get("boundary") is not None:     # the boundary fitted with the chosen theta
            problem.g = info["boundary"]
        refit_std = theta_tv = None
        refit_skipped = False       # the refit's partition had more than TV_REFIT_MAX_REGIONS regions
        theta_part = None       # the TV solution the calibration check partitions (before the refit)
        text = ""
        if TV_REWEIGHT is not None and dim == 2 and regularization == "tv":
            # debiased TV (TV_REWEIGHT): one solve more at the chosen beta, from its solution; the rule's gamma and
            # the Laplace step keep the data Hessian of the plain-TV solution (computed by the rule; the same mesh
            # and data, a modulus that differs mostly in the inclusions' contrast)
            def accept(theta_r, info_r):
                nonlocal theta, info
                if np.all(np.isfinite(theta_r)):
                    theta, info = theta_r, dict(info_r, boundary=info_r.get("boundary"))
                    if info.get("boundary") is not None:
                        problem.g = info["boundary"]

            for _ in range(TV_REWEIGHT_STEPS):
                reg.reweight(theta, TV_REWEIGHT)
                accept(*_optimise(problem, theta, b, maxiter=maxiter, gtol=gtol))   # the bar is closed here
            if TV_BREGMAN:
                # Bregman iteration (TV_BREGMAN, option): R(theta) - p.theta with p the subgradient of R at the
                # previous iterate (= p_k - grad misfit / beta at its optimum), each solve adding back what the last
                # one shrank
                b_breg = b * TV_BREGMAN_START
                phi_floor = problem.misfit(cand[1])[0] if TV_BREGMAN_START != 1.0 else -np.inf
                if TV_BREGMAN_START != 1.0:
                    accept(*_optimise(problem, theta, b_breg, maxiter=maxiter, gtol=gtol))
                for _ in range(TV_BREGMAN):
                    if problem.misfit(theta)[0] <= phi_floor:
                        break
                    reg.linear = reg(theta)[1] * TV_BREGMAN_FRACTION
                    try:
                        accept(*_optimise(problem, theta, b_breg, maxiter=maxiter, gtol=gtol))
                    finally:
                        reg.linear = None
            passes = "once" if TV_REWEIGHT_STEPS == 1 else f"{TV_REWEIGHT_STEPS} times"
            text += f"; TV reweighted {passes} (1 / (1 + |jump| / {TV_REWEIGHT:g}))"
            if TV_REFIT:
                # region debias refit (TV_REFIT): one log mu per region of the TV solution, fitted to the misfit
                # alone where the data constrain it
                theta_tv = theta if TV_REFIT_STD else None
                theta_part = theta
                theta, refit = region_refit(theta)
                refit_std = refit["std_elements"]
                refit_skipped = bool(refit["too_many"])
                done = [e for e in refit["candidates"] if e["applied"]]
                text += (f"; region refit (level {TV_REFIT:g}): not applied, {refit['regions'] - 1} regions "
                         f"besides the reference (more than {TV_REFIT_MAX_REGIONS}: not piecewise constant)"
                         if refit["too_many"] else
                         f"; region refit (level {TV_REFIT:g}): {len(done)} of {len(refit['candidates'])} regions, "
                         f"log mu changed by {[round(e['shift'], 3) for e in done]}")
            phi, _ = problem.misfit(theta)
            R, _ = reg(theta)
            if TV_BREGMAN:
                text += (f"; Bregman iteration, at most {TV_BREGMAN} steps at beta {b * TV_BREGMAN_START:.3g}, "
                         f"fraction {TV_BREGMAN_FRACTION:g}")
        return theta, info, phi, R, theta_part, theta_tv, refit_std, refit_skipped, text

    b = chosen[0]
    (theta, info, phi, R, theta_part, theta_tv, refit_std, refit_skipped, text) = debiased(chosen)
    area_el = fem.basis.dx.sum(axis=1)      # element areas (mm^2)
    rule_base, rule = rule, rule + text
    # the bracket's smaller beta (gamma at or above the target) against its larger one (below it): both lie within
    # half a decade of the target, which cannot tell them apart; where the smaller one's image shows what the data
    # do not (DOF_STEP_BACK), its extra parameters fitted the noise, and the larger one is taken if its image does not
    larger = runs[-1] if runs and runs[-1][0] > b else above
    if (DOF_STEP_BACK and beta is None and beta_method in ("dof", "dof-area") and larger is not None
            and dim == 2 and regularization == "tv" and TV_REWEIGHT is not None and images is None
            and next((e.get("gamma", -1.0) for e in sweep if e["beta"] == b), -1.0) >= target_dof):
        why = _overfit_reason(theta, theta_part, refit_skipped, reg, el_strain, mesh, area_el, h)
        if why:
            keep = (reg.length.copy(), None if problem.g is None else np.array(problem.g, copy=True))
            alt = debiased(larger)
            why_alt = _overfit_reason(alt[0], alt[4], alt[7], reg, el_strain, mesh, area_el, h)
            if not why_alt:
                chosen = larger
                b = larger[0]
                (theta, info, phi, R, theta_part, theta_tv, refit_std, refit_skipped, text) = alt
                rule = (rule_base + f"; stepped back to the bracket's larger beta {b:.3g} (gamma "
                        f"{next(e['gamma'] for e in sweep if e['beta'] == b):.3g}): at the smaller one {why}" + text)
            else:
                reg.length = keep[0]
                if keep[1] is not None:
                    problem.g = keep[1]
                rule += f"; the bracket's larger beta {larger[0]:.3g} was tried too ({why_alt}) and not taken"
    support = None      # (fraction, regions) of the TV solution's unsupported regions, before any merge
    if SUPPORT_MERGE and refit_std is not None and not refit_skipped and images is None:
        # a region whose modulus step the axial strain does not show (_unsupported_regions) has no evidence in the
        # data for its step: it takes the background's level, and the region refit runs again, so that the other
        # regions are fitted against a background without it (SUPPORT_MERGE)
        part_m = _calibration_partition(theta_part, reg, h * h)
        support = _unsupported_regions(theta_part, theta, reg, el_strain, mesh, area_el, h * h, partition=part_m)
        if support[1]:
            inner_m = inner_elements(mesh)
            ref_m = inner_m & ~np.isin(part_m[0], part_m[1])
            t0 = float(np.sum(area_el[ref_m] * theta[ref_m]) / np.sum(area_el[ref_m]))
            gone = np.isin(part_m[0], [r[3] for r in support[1]])
            theta, refit2 = region_refit(np.where(gone, t0, theta))
            std2 = refit2["std_elements"]
            # the merged elements are background now: the Laplace std (NaN here), the refitted ones the new std
            refit_std = np.where(np.isfinite(std2), std2, np.where(gone, np.nan, refit_std))
            done2 = [e for e in refit2["candidates"] if e["applied"]]
            rule += (f"; {len(support[1])} region(s) the axial strain does not support set to the background's "
                     f"level, refit again: {len(done2)} of {len(refit2['candidates'])} regions, log mu changed by "
                     f"{[round(e['shift'], 3) for e in done2]}")
            phi, _ = problem.misfit(theta)
            R, _ = reg(theta)
    if theta_part is None:
        theta_part = theta
    q5, q95 = np.percentile(theta, [5, 95])
    flat = q95 - q5 < np.log(CONTRAST_REGION)     # at the large edge a flat image hides nothing it shows
    # the dof rules at the largest beta tried: an edge only when even that beta leaves gamma above the target; with
    # gamma below it there and above it at the next beta, the target lies inside the grid and the largest is nearer
    g_b = next((e.get("gamma") for e in sweep if e["beta"] == b), None)
    bracketed = (beta_method in ("dof", "dof-area") and g_b is not None and g_b <= target_dof
                 and any(e.get("gamma", -1.0) >= target_dof for e in sweep))
    stopped = sweep[-1] if beta is None and sweep and sweep[-1].get("stop") else None
    if beta is None and len(grid) > 1 and (b == grid[-1] or (b == grid[0] and not flat and not bracketed)):
        if stopped is not None and b == grid[0]:
            # the rule did not run out of grid: it stopped because the next solve did not converge, so its target
            # is not bracketed (say so: a larger maxiter may let the rule go on)
            flags.append(f"beta {b:.3g} is the largest of its grid {[float(f'{x:.3g}') for x in grid]} and the "
                         f"solve at the next beta {stopped['beta']:.3g} did not converge ({stopped['message']}): "
                         "the rule could not bracket its target")
        else:
            flags.append(f"beta {b:.3g} is at the {'small' if b == grid[-1] else 'large'} edge of its grid "
                         f"{[float(f'{x:.3g}') for x in grid]}: the rule found no beta inside it")
        rule += " [at the grid's edge]"
    t_opt = time.perf_counter() - t
    one_step = None
    if images is not None:
        t = time.perf_counter()
        c0 = time.process_time()
        term = _image_term(displacement, mesh, images)
        # the boundary values of the two-step result (the data, or the fitted boundary of 3D data)
        bnd = problem.dirichlet
        mu0 = np.exp(theta)
        u0, lu0 = fem.solve(mu0, bnd)
        S = _Jacobian(fem, mu0, u0, lu0, ONE_STEP_DENSE_LIMIT)
        HII = sp.csr_matrix(term.hessian())[fem.I][:, fem.I]
        tr_psi = S.gram_trace(HII)
        scale = float(tr_psi * s2 / max(S.gram_trace(fem.M[fem.I][:, fem.I]), 1e-300))
        del S
        psi_two = term.energy(u0)
        theta, info1 = _one_step(fem, reg, bnd, theta, b, term, scale, trace=tr_psi)
        u1, _ = fem.solve(np.exp(theta), bnd)
        one_step = {"psi_two_step": psi_two, "psi_one_step": term.energy(u1), "nit": info1["nit"],
                    "objective_two_step": info1["objective_start"], "objective_one_step": info1["objective"],
                    "message": info1["message"], "seconds": time.perf_counter() - t,
                    "cpu_seconds": time.process_time() - c0, "cg_iterations": info1["cg_iterations"]}
        if not info1["success"]:
            flags.append(f"one-step inversion: {info1['message']}")
        phi, _ = problem.misfit(theta)
        R, _ = reg(theta)

    mu = np.exp(theta)
    med = _weighted_median(mu, area_el)
    ok = bool(info["success"]) and np.all(np.isfinite(mu)) and med > 0
    message = info["message"]
    if np.any(np.abs(theta) >= THETA_BOUND - 1e-6):
        ok = False
        message = f"log-modulus reached its bound |log mu| = {THETA_BOUND:g} ({message})"
    u_model, _ = fem.solve(mu, problem.dirichlet)
    # the misfit in units of the *model's* strain: noise inflates the data's own RMS strain (and with it s^2),
    # the model's smooth field does not
    el_model, eps_model = _element_strain(fem.basis, u_model)
    # 2D: the model's lateral expansion against the data's (MODEL_RATIO_TOLERANCE); 3D data carry no model choice
    # to check
    short, why_short = (_lateral_shortfall(el_strain, el_model, mesh, area_el, model) if dim == 2
                        else (float("nan"), ""))
    phi_model = phi * (eps_rms / eps_model) ** 2 if eps_model > 0 else np.inf
    if np.isfinite(phi) and phi_model > MISFIT_LIMIT:
        flags.append(f"the misfit {phi_model:.3g} stays well above the noise level of registered fields (limit "
                     f"{MISFIT_LIMIT:g}, in units of the model's squared displacement change across one element): "
                     f"the {model} model does not explain the data")
    if why_short:
        flags.append(why_short)
    if ok and not flags:
        why = _contradiction(mu / med, el_strain, mesh, area_el)
        if why:
            flags.append(f"modulus contradicts strain: {why}")
    unsupported_area, notes = np.nan, []
    # 3D and Tikhonov: neither the strain support nor the calibration is assessed (measured on 2D TV images only)
    checked = dim == 2 and regularization == "tv"
    # the regions of the TV solution before the refit, read by the strain support and the calibration check
    partition = _calibration_partition(theta_part, reg, h * h) if checked else None
    if checked:
        # a region whose modulus step the axial strain does not show (SUPPORT_FRACTION): over a large part of the
        # image the background's level, and every contrast read against it, is the inversion's, not the data's
        frac, regs = (support if support is not None else
                      _unsupported_regions(theta_part, theta, reg, el_strain, mesh, area_el, h * h,
                                           partition=partition))
        unsupported_area = frac
        if regs:
            what = (f"{len(regs)} region(s) of {sum(r[0] for r in regs):.3g} mm^2 ({100 * frac:.0f} % of the inner "
                    "area; " + ", ".join(f"{r[0]:.3g} mm^2 at mu {r[1]:.3g} x the background, |e_xx| {r[2]:.3g} x"
                                         for r in regs[:3]) + ") whose modulus step the axial strain does not show")
            if UNSUPPORTED_AREA is not None and frac > UNSUPPORTED_AREA and refit_skipped:
                flags.append(f"{what}, and the image is not a few regions (the region refit was not applied): "
                             "its levels are the regulariser's (e.g. at a low SNR); the contrast is not reliable")
            elif support is not None:
                notes.append(f"modulus not supported by strain: {what}; set to the background's level and the "
                             "other regions refitted against it (SUPPORT_MERGE)")
            else:
                notes.append(f"modulus not supported by strain: {what}; read them as artefacts of the inversion")
    if flags:
        ok = False
        message = "FLAGGED: " + "; ".join(flags) + f" (optimiser: {message})"
    hist = np.asarray(info["history"], float).reshape(-1, 3)
    t = time.perf_counter()
    std = constrained = std_laplace = None
    if uncertainty and dim == 3 and fem.I.size * fem.n_el > LAPLACE_DENSE_LIMIT:
        constrained = _constrained_blocks(fem, problem, theta)      # too large for the dense Laplace step
    elif uncertainty:
        std, constrained = _laplace(fem, reg, problem, theta if theta_tv is None else theta_tv, b,
                                    n_data=fem.I.size,
                                    Hd=hd_cache.get(b) if images is None else None)
        if std is not None:
            std = std * _registered_factor(displacement, h, dim)
        std_laplace = std
        if TV_REFIT_STD and refit_std is not None and std is not None:
            # refitted regions (TV_REFIT): the region model's std, one value per region (_region_refit)
            use = np.isfinite(refit_std) & np.isfinite(std)
            std = np.where(use, refit_std, std)
    calibrated = True if checked else None
    n_regions = len(partition[1]) if checked and std is not None else 0
    if n_regions > CALIBRATION_MAX_REGIONS and std is not None:
        # not a few inclusions in a background: the std misses the regulariser's bias (CALIBRATION_MAX_REGIONS)
        calibrated = False
        if UNCALIBRATED_SPREAD:
            ok_s = np.isfinite(std)
            spread = _robust_spread(theta[ok_s]) if ok_s.any() else 0.0
            std = np.sqrt(std ** 2 + (UNCALIBRATED_SPREAD * spread) ** 2)
            bias = (f"; a bias term {UNCALIBRATED_SPREAD:g} x the spread of log mu ({spread:.3g}) is added in "
                    "quadrature (on registered random tissue 23 -> 62 % of the true log mu within +-1 sigma, per "
                    "image 38-99 %): read the error bars as approximate")
        else:
            bias = "; read it as a lower bound"
        notes.append(f"uncertainty not calibrated: the modulus image has {n_regions} regions besides the largest "
                     f"(more than {CALIBRATION_MAX_REGIONS} at level {CALIBRATION_LEVEL:g}, each at least "
                     f"{CALIBRATION_MIN_AREA:g} mm^2): not a few inclusions "
                     "in a uniform background, where the Laplace std was calibrated; on tissue whose stiffness "
                     "varies everywhere it misses the regulariser's bias" + bias)
    scale = None
    if calibrated and SCATTER_FLOOR and std is not None:
        # a calibrated 2D TV std: at least the background's own scatter (SCATTER_FLOOR)
        scale = _scatter_factor(theta, std_laplace, partition[0], partition[1], constrained)
        refitted = (np.isfinite(refit_std) & np.isfinite(std_laplace) if TV_REFIT_STD and refit_std is not None
                    else np.zeros(std.size, bool))
        std = np.where(refitted & (not SCATTER_FLOOR_REFITTED), std, std * scale)
    t_unc = time.perf_counter() - t
    mu_kpa = None
    if ref is not None:
        bounds, e_kpa = ref
        sel = _reference_elements(mesh, bounds)
        m_ref = float(np.sum(area_el[sel] * mu[sel]) / np.sum(area_el[sel]))
        mu_kpa = mu / m_ref * (e_kpa / 3.0)
    return InversionResult(
        mesh=mesh, mu=mu / med, model=model, lambda_bar=lb, beta=b, beta_rule=rule, sweep=sweep,
        regularization=regularization, weights=tuple(w), u_measured=d, u_model=u_model,
        strain_measured=el_strain, misfit=phi, regularizer_value=R, history=hist, success=ok, message=message,
        nit=int(info["nit"]), timings={"setup": t_setup, "optimise": t_opt, "uncertainty": t_unc,
                                       "total": time.perf_counter() - t_all, "n_evaluations": problem.n_eval},
        model_rule=model_rule, mesh_rule=mesh_rule, strain_ratio=ratio, flags=flags, uncertainty=std,
        constrained=constrained,
        shear_modulus_kpa=mu_kpa, reference=None if ref is None else [list(ref[0]), ref[1]], one_step=one_step,
        misfit_model_strain=phi_model, lateral_shortfall=short, uncertainty_calibrated=calibrated, notes=notes,
        unsupported_area=unsupported_area, uncertainty_scale=scale)


def _overfit_reason(theta, theta_part, refit_skipped, reg, el_strain, mesh, area_el, h) -> str:
    """Why a debiased 2D TV image shows more than its data support (:data:`DOF_STEP_BACK`), else ''.

    ``theta`` (n_el,) the result's log mu, ``theta_part`` (n_el,) the TV solution before the region refit (None:
    ``theta``), ``refit_skipped`` whether the refit was skipped (too many regions), ``el_strain`` (n_el, 3) the data's
    element strain, ``area_el`` (n_el,) element areas mm^2, ``h`` the mean element size mm.  Reasons, in this order:
    the modulus contradicts the axial strain (:func:`_contradiction`, the flag's test: eq:meq's stiffer region must
    strain less); the TV solution is not a few regions (more than :data:`CALIBRATION_MAX_REGIONS` of
    :func:`_calibration_partition`); unsupported regions (:func:`_unsupported_regions`) cover more than
    :data:`UNSUPPORTED_AREA` of an image whose refit was skipped (the flag's condition)."""
    tp = theta if theta_part is None else theta_part
    mu = np.exp(theta)
    if _contradiction(mu / _weighted_median(mu, area_el), el_strain, mesh, area_el):
        return "its modulus contradicts the strain"
    part = _calibration_partition(tp, reg, h * h)
    if len(part[1]) > CALIBRATION_MAX_REGIONS:
        return f"its TV image has {len(part[1])} regions besides the largest (more than {CALIBRATION_MAX_REGIONS})"
    frac, _ = _unsupported_regions(tp, theta, reg, el_strain, mesh, area_el, h * h, partition=part)
    if UNSUPPORTED_AREA is not None and frac > UNSUPPORTED_AREA and refit_skipped:
        return f"{100 * frac:.0f} % of it is not supported by the strain"
    return ""


def _calibration_partition(theta, reg, element_area: float):
    """(labels (n_el,), candidates) of the log-modulus image ``theta`` (n_el,): :func:`_regions` at
    :data:`CALIBRATION_LEVEL`, a component smaller than :data:`CALIBRATION_MIN_AREA` mm^2, or than
    :data:`TV_REFIT_MIN_ELEMENTS` elements, joining a neighbour; ``element_area`` the mean element area (mm^2)."""
    min_el = max(TV_REFIT_MIN_ELEMENTS, int(np.ceil(CALIBRATION_MIN_AREA / max(float(element_area), 1e-12))))
    labels, cand, _ = _regions(np.asarray(theta, float), reg, CALIBRATION_LEVEL, min_el)
    return labels, cand


def _calibration_regions(theta, reg, element_area: float) -> int:
    """Regions of the log-modulus image ``theta`` besides the largest (:func:`_calibration_partition`): the count
    of :data:`CALIBRATION_MAX_REGIONS`."""
    return len(_calibration_partition(theta, reg, element_area)[1])


def _unsupported_regions(theta_part, theta, reg, el_strain, mesh, area_el, element_area: float, partition=None):
    """Regions of a 2D TV image whose modulus step the axial strain does not show: (fraction of the inner
    elements' area they cover, list of (area mm^2, mu / the largest region's, abs(e_xx) / the largest region's)).

    The partition is :func:`_calibration_partition`'s (``theta_part``, the TV solution before the refit: level
    :data:`CALIBRATION_LEVEL`, regions of at least :data:`CALIBRATION_MIN_AREA` mm^2, ``element_area`` the mean
    element area; ``partition`` when the caller has it already); each region's step d = mean log mu (``theta``, the result) minus the largest region's, and its
    strain support s = log(mean abs(e_xx) of the largest / of the region) (area-weighted, inner elements only, as
    :func:`_contradiction`: the boundary elements carry the data's edge).  A region is unsupported when
    |d| >= :data:`SUPPORT_LEVEL` and s / d < :data:`SUPPORT_FRACTION`: a stiffer region must strain less, a softer
    more, whatever its shape (the strain of a disk of contrast c, 2 / (1 + c) of the far field in plane strain,
    gives s / d of 0.3-0.8 for c 1/8-8)."""
    labels, cand = partition if partition is not None else _calibration_partition(theta_part, reg, element_area)
    inner = inner_elements(mesh)
    if inner.sum() < 8 or not cand:
        return 0.0, []
    ax = np.abs(el_strain[:, 0])
    ref = inner & ~np.isin(labels, cand)

    def mean(v, sel):
        return float(np.sum(area_el[sel] * v[sel]) / np.sum(area_el[sel]))

    if ref.sum() < 2 or not mean(ax, ref) > 0:
        return 0.0, []
    t0, e0 = mean(theta, ref), mean(ax, ref)
    out = []
    for k in cand:
        sel = inner & (labels == k)
        a = float(area_el[sel].sum())
        if a < CALIBRATION_MIN_AREA or sel.sum() < 2:
            continue
        d, e = mean(theta, sel) - t0, mean(ax, sel)
        if abs(d) >= SUPPORT_LEVEL and e > 0 and np.log(e0 / e) / d < SUPPORT_FRACTION:
            out.append((a, float(np.exp(d)), e / e0, int(k)))
    return float(sum(x[0] for x in out) / area_el[inner].sum()), out


def _scatter_factor(theta, std, labels, candidates, constrained) -> float:
    """The scatter floor's factor on a calibrated 2D TV std (:data:`SCATTER_FLOOR`): max(1, s / r), s the robust
    spread (:func:`_robust_spread`) of ``theta`` (log mu, (n_el,)) over the background, r the RMS of ``std``
    (the Laplace std of log mu, (n_el,)) over the same elements.  The background: the elements of the largest
    region of the partition (``labels`` (n_el,), ``candidates`` the other regions' labels;
    :func:`_calibration_partition`) that are ``constrained`` with a finite std; 1 with fewer than
    :data:`SCATTER_FLOOR_MIN_ELEMENTS` of them."""
    theta, std = np.asarray(theta, float), np.asarray(std, float)
    bg = ~np.isin(labels, candidates) & np.asarray(constrained, bool) & np.isfinite(std) & np.isfinite(theta)
    if bg.sum() < SCATTER_FLOOR_MIN_ELEMENTS:
        return 1.0
    rms = float(np.sqrt(np.mean(std[bg] ** 2)))
    if not rms > 0:
        return 1.0
    return float(max(1.0, _robust_spread(theta[bg]) / rms))


def _robust_spread(v) -> float:
    """1.4826 x the median absolute deviation of ``v`` (the std of a normal sample, robust to a few outliers)."""
    v = np.asarray(v, float)
    return float(1.4826 * np.median(np.abs(v - np.median(v)))) if v.size else 0.0


class InversionResult:
    """A relative shear-modulus image on a quad mesh (:func:`invert`).

    Attributes
    ----------
    mesh : skfem.MeshQuad1
        mm; ``p[0]`` axial x, ``p[1]`` lateral y.
    mu : (n_el,) float
        Element values of the shear modulus, normalised to an area-weighted median of 1 over the region.
    model, lambda_bar : str, float
        Forward model and its :math:`\\bar\\lambda` (eq:cEq).
    beta, beta_rule, sweep
        Regularisation weight, how it was chosen, and the (beta, misfit, regulariser) table of the rule.
    u_measured, u_model : (2 n_nodes,) float, mm
        Nodal displacement (interleaved ux, uy): the data, and the forward model's at the solution.
    strain_measured : (n_el, 3)
        Element-mean strain [exx, eyy, exy] of the data.
    misfit, regularizer_value : float
        The two terms of J at the solution (misfit without beta, dimensionless).
    lateral_shortfall : float
        How much less the model's field expands laterally than the data's, the smallest over the image's four
        quadrants (:func:`_lateral_shortfall`; flagged above :data:`MODEL_RATIO_TOLERANCE`; NaN in 3D).
    misfit_model_strain : float
        The misfit in units of the model's (not the data's) RMS strain, the quantity of the misfit flag
        (:data:`MISFIT_LIMIT`).
    history : (nit, 3) float
        J, misfit, regulariser per L-BFGS-B iteration of the chosen beta.
    success, message, nit, timings
    flags : list of str
        Why ``success`` is False beyond the optimiser (beta at its grid's edge, model against the data's strain
        ratio, modulus against strain).
    model_rule, strain_ratio
        How the model was chosen, and the data's lateral/axial strain ratio (:func:`strain_ratio`).
    mesh_rule : str
        Which inversion mesh was used (the registration's own, or a tensor mesh and its element size).
    uncertainty : (n_el,) float or None
        Standard deviation of log mu per element (Laplace approximation), NaN where not ``constrained``.
        It is the noise's spread at the chosen beta, not the regulariser's bias: calibrated on inclusions
        (55-80 % of the true log mu within +-1 sigma), over-confident on tissue whose stiffness varies within
        two elements (23 %, docs/inversion.md "Heterogeneous tissue"), where ``uncertainty_calibrated`` is False
        and a bias term is added (62 %).  Where calibrated (2D TV), at least the background's own scatter: the
        std times ``uncertainty_scale`` (:data:`SCATTER_FLOOR`).
    constrained : (n_el,) bool or None
        Elements the data constrain.
    uncertainty_calibrated : bool or None
        False when the modulus image is not a few inclusions in a uniform background (more than
        :data:`CALIBRATION_MAX_REGIONS` regions), where ``uncertainty`` misses the regulariser's bias (``notes``
        says so, and ``uncertainty`` carries the bias term of :data:`UNCALIBRATED_SPREAD`); True otherwise or
        without ``uncertainty``; None where not assessed (3D and Tikhonov results, files written before the
        check).  Not a flag:
        ``success`` is about the modulus, this about its error bars.
    notes : list of str
        Remarks that do not make the result fail (the uncalibrated uncertainty, regions the strain does not
        support on a small part of the image).
    uncertainty_scale : float or None
        The scatter floor's factor (>= 1) on ``uncertainty`` (:func:`_scatter_factor`, :data:`SCATTER_FLOOR`): the
        robust spread of log mu over the background against the RMS of its Laplace std, 1 where the std already
        covers it; None where not applied (no uncertainty, 3D, Tikhonov, an uncalibrated image, the floor off,
        files written before it).
    unsupported_area : float
        Fraction of the inner elements' area in regions whose modulus step the axial strain does not show
        (:func:`_unsupported_regions`; above :data:`UNSUPPORTED_AREA` a flag); NaN where not assessed (3D,
        Tikhonov, files written before the check).
    shear_modulus_kpa, youngs_modulus_kpa : (n_el,) float or None
        Absolute moduli, kPa, with ``reference`` (:func:`invert`).
    one_step : dict or None
        With images or volumes (:func:`invert`): image term and objective before / after the one-step inversion,
        Gauss-Newton (and conjugate-gradient) iterations, seconds and CPU seconds.
    """

    def __init__(self, *, mesh, mu, model, lambda_bar, beta, beta_rule="", sweep=(), regularization="tv",
                 weights=DEFAULT_WEIGHTS, u_measured=None, u_model=None, strain_measured=None, misfit=np.nan,
                 regularizer_value=np.nan, history=(), success=False, message="", nit=0, timings=None,
                 model_rule="", mesh_rule="", strain_ratio=np.nan, flags=(), uncertainty=None, constrained=None,
                 shear_modulus_kpa=None, reference=None, one_step=None, misfit_model_strain=np.nan,
                 lateral_shortfall=np.nan, uncertainty_calibrated=True, notes=(), unsupported_area=np.nan,
                 uncertainty_scale=None):
        self.mesh = mesh
        self.mu = np.asarray(mu, float)
        self.model = str(model)
        self.lambda_bar = float(lambda_bar)
        self.beta = float(beta)
        self.beta_rule = str(beta_rule)
        self.sweep = list(sweep)
        self.regularization = str(regularization)
        self.weights = tuple(float(x) for x in weights)
        n2 = mesh.p.shape[0] * mesh.p.shape[1]
        self.u_measured = np.zeros(n2) if u_measured is None else np.asarray(u_measured, float)
        self.u_model = np.full(n2, np.nan) if u_model is None else np.asarray(u_model, float)
        self.strain_measured = (np.full((mesh.t.shape[1], 3 if mesh.p.shape[0] == 2 else 6), np.nan)
                                if strain_measured is None else np.asarray(strain_measured, float))
        self.misfit = float(misfit)
        self.regularizer_value = float(regularizer_value)
        self.history = np.asarray(history, float).reshape(-1, 3)
        self.success = bool(success)
        self.message = str(message)
        self.nit = int(nit)
        self.timings = dict(timings or {})
        self.model_rule = str(model_rule)
        self.mesh_rule = str(mesh_rule)
        self.strain_ratio = float(strain_ratio)
        self.flags = list(flags)
        n_el = mesh.t.shape[1]
        self.uncertainty = None if uncertainty is None else np.asarray(uncertainty, float).reshape(n_el)
        self.constrained = None if constrained is None else np.asarray(constrained, bool).reshape(n_el)
        self.shear_modulus_kpa = None if shear_modulus_kpa is None else np.asarray(shear_modulus_kpa, float)
        self.reference = reference
        self.one_step = one_step
        self.misfit_model_strain = float(misfit_model_strain)
        self.lateral_shortfall = float(lateral_shortfall)
        self.uncertainty_calibrated = None if uncertainty_calibrated is None else bool(uncertainty_calibrated)
        self.notes = list(notes)
        self.unsupported_area = float(unsupported_area)
        self.uncertainty_scale = None if uncertainty_scale is None else float(uncertainty_scale)
        self._locator = None

    @property
    def youngs_modulus_kpa(self):
        """E = 3 mu in kPa (incompressible), (n_el,); None without ``reference``."""
        return None if self.shear_modulus_kpa is None else 3.0 * self.shear_modulus_kpa

    @property
    def element_values(self) -> np.ndarray:
        """Alias of :attr:`mu`: (n_el,) shear modulus per element (relative, median 1)."""
        return self.mu

    @property
    def centroids(self) -> np.ndarray:
        """Element centres (n_el, 2) mm ((n_el, 3) for a 3D result)."""
        return self.mesh.p[:, self.mesh.t].mean(axis=1).T

    @property
    def dim(self) -> int:
        """2 (quads) or 3 (hexahedra)."""
        return int(self.mesh.p.shape[0])

    @property
    def strain_components(self) -> tuple:
        """Names of the columns of :attr:`strain_measured`."""
        return ("exx", "eyy", "exy") if self.dim == 2 else STRAIN_COMPONENTS_3D

    def shear_modulus(self, points) -> np.ndarray:
        """Relative shear modulus at ``points`` (n, 2) [x, y] mm (3D: (n, 3) [x, y, z]) -> (n,); NaN outside the
        mesh (a point on an element edge takes one of its elements)."""
        from .pixels import PointLocator

        if self.dim == 3:
            return self._shear_modulus_3d(points)
        pts = np.asarray(points, float)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise InputError(f"points must have shape (n, 2) [x, y] mm, got {pts.shape}")
        if self._locator is None:
            self._locator = PointLocator(self.mesh)
        out = np.full(len(pts), np.nan)
        ok = np.all(np.isfinite(pts), axis=1)
        if ok.any():
            loc = self._locator.locate(pts[ok])
            vals = np.full(int(ok.sum()), np.nan)
            vals[loc.inside] = self.mu[loc.element]
            out[ok] = vals
        return out

    def _shear_modulus_3d(self, points) -> np.ndarray:
        # hexahedra of a tensor mesh are axis-aligned boxes: the nearest centres, then a bounding-box test
        from scipy.spatial import cKDTree

        pts = np.asarray(points, float)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"points must have shape (n, 3) [x, y, z] mm for a 3D result, got {pts.shape}")
        if self._locator is None:
            P = self.mesh.p[:, self.mesh.t]
            self._locator = (cKDTree(self.centroids), P.min(axis=1).T, P.max(axis=1).T)
        tree, lo, hi = self._locator
        out = np.full(len(pts), np.nan)
        ok = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
        if ok.size:
            k = min(8, self.mesh.t.shape[1])
            _, cand = tree.query(pts[ok], k=k)
            cand = cand.reshape(len(ok), k)
            tol = 1e-9 * (1.0 + np.abs(pts[ok]).max(axis=1))[:, None, None]
            q = pts[ok][:, None, :]
            inside = np.all((q >= lo[cand] - tol) & (q <= hi[cand] + tol), axis=2)
            hit = inside.any(axis=1)
            first = cand[np.arange(len(ok)), np.argmax(inside, axis=1)]
            out[ok[hit]] = self.mu[first[hit]]
        return out

    # -- files ----------------------------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write ``.npz`` (reloadable with :func:`load_inversion`; keys mesh_points (2, n_nodes), mesh_cells
        (4, n_el), mu (n_el,), u_measured, u_model (2 n_nodes,), strain_measured (n_el, 3), history, ...; a 3D
        result: (3, n_nodes), (8, n_el) hexahedra, (3 n_nodes,), (n_el, 6))."""
        from ._atomic import atomic_savez

        path = Path(path)
        if path.suffix.lower() != ".npz":
            raise InputError(f"inversion results are saved as .npz, got {path}")
        meta = {"model": self.model, "lambda_bar": self.lambda_bar, "beta": self.beta, "beta_rule": self.beta_rule,
                "sweep": self.sweep, "regularization": self.regularization, "weights": self.weights,
                "misfit": self.misfit, "regularizer_value": self.regularizer_value, "success": self.success,
                "message": self.message, "nit": self.nit, "timings": self.timings, "model_rule": self.model_rule,
                "mesh_rule": self.mesh_rule, "strain_ratio": self.strain_ratio, "flags": self.flags,
                "reference": self.reference, "one_step": self.one_step,
                "misfit_model_strain": self.misfit_model_strain, "lateral_shortfall": self.lateral_shortfall,
                "uncertainty_calibrated": self.uncertainty_calibrated, "notes": self.notes,
                "unsupported_area": self.unsupported_area, "uncertainty_scale": self.uncertainty_scale}
        extra = {}
        if self.uncertainty is not None:
            extra["uncertainty"] = self.uncertainty
        if self.constrained is not None:
            extra["constrained"] = self.constrained
        if self.shear_modulus_kpa is not None:
            extra["shear_modulus_kpa"] = self.shear_modulus_kpa
        atomic_savez(path, format=np.str_(_FORMAT), mesh_points=np.asarray(self.mesh.p, float),
                     mesh_cells=np.asarray(self.mesh.t, np.int64), mu=self.mu, u_measured=self.u_measured,
                     u_model=self.u_model, strain_measured=self.strain_measured, history=self.history,
                     meta=np.str_(json.dumps(meta, default=float)), **extra)
        return path

    def to_vtu(self, path) -> Path:
        """ParaView file (meshio): quads with cell data shear_modulus, log_shear_modulus, exx/eyy/exy (measured)
        and point data displacement_measured / displacement_model (n_nodes, 3) mm."""
        from .optional import require

        meshio = require("meshio", feature="InversionResult.to_vtu")

        path = Path(path)
        if self.dim == 3:
            return self._to_vtu_3d(meshio, path)
        p = self.mesh.p
        pts = np.column_stack([p[0], p[1], np.zeros(p.shape[1])])
        z = np.zeros(p.shape[1])
        um = np.column_stack([self.u_measured[0::2], self.u_measured[1::2], z])
        uf = np.column_stack([self.u_model[0::2], self.u_model[1::2], z])
        cd = {"shear_modulus": [self.mu], "log_shear_modulus": [np.log(self.mu)],
              **({} if self.uncertainty is None else {"std_log_shear_modulus": [self.uncertainty]}),
              "exx": [self.strain_measured[:, 0]], "eyy": [self.strain_measured[:, 1]],
              "exy": [self.strain_measured[:, 2]]}
        meshio.write(str(path), meshio.Mesh(pts, [("quad", self.mesh.t.T.astype(np.int64))],
                                            point_data={"displacement_measured": um, "displacement_model": uf},
                                            cell_data=cd))
        return path

    def _to_vtu_3d(self, meshio, path) -> Path:
        from skfem.io.meshio import HEX_MAPPING

        cd = {"shear_modulus": [self.mu], "log_shear_modulus": [np.log(self.mu)],
              **({} if self.uncertainty is None else {"std_log_shear_modulus": [self.uncertainty]}),
              **{name: [self.strain_measured[:, k]] for k, name in enumerate(STRAIN_COMPONENTS_3D)}}
        cells = self.mesh.t[HEX_MAPPING[:8]].T.astype(np.int64)     # scikit-fem's hexahedron node order -> VTK's
        meshio.write(str(path), meshio.Mesh(self.mesh.p.T, [("hexahedron", cells)],
                                            point_data={"displacement_measured": self.u_measured.reshape(-1, 3),
                                                        "displacement_model": self.u_model.reshape(-1, 3)},
                                            cell_data=cd))
        return path

    def plot(self, out_png=None, **kw):
        """The modulus image beside the measured axial strain (:func:`femreg.plot.plot_inversion`); a 3D result:
        three orthogonal slices through ``at=`` of the modulus, its uncertainty and the axial strain
        (:func:`femreg.volplot.plot_inversion_volume`)."""
        if self.dim == 3:
            from .volplot import plot_inversion_volume

            return plot_inversion_volume(self, out_png, **kw)
        from .plot import plot_inversion

        return plot_inversion(self, out_png, **kw)

    def __repr__(self) -> str:
        return self.summary()

    def summary(self, message: bool = True) -> str:
        """One line: model, beta, elements, the 5-95 % range of mu, the verdict and (``message``) the message
        (the CLI leaves it out where it prints the message on its own line)."""
        q = np.percentile(self.mu, [5, 95])
        return (f"InversionResult(model={self.model!r}, beta={self.beta:.3g}, n_el={self.mesh.t.shape[1]}, "
                f"mu 5-95 % {q[0]:.3g}-{q[1]:.3g}, success={self.success}, nit={self.nit}"
                + (f", message={self.message!r})" if message else ")"))


def is_inversion_file(path) -> bool:
    """True when ``path`` is an ``.npz`` written by :meth:`InversionResult.save`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return "format" in z.files and str(z["format"]) == _FORMAT
    except Exception:  # noqa: BLE001 - anything unreadable is not one
        return False


def load_inversion(path) -> InversionResult:
    """Read a file written by :meth:`InversionResult.save`."""
    from skfem import MeshHex1, MeshQuad1

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no inversion file {str(path)!r}")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "format" not in z.files or str(z["format"]) != _FORMAT:
                reg = all(k in z.files for k in ("u", "mesh_points", "spacing"))
                raise FileFormatError(f"{path}: not a femreg inversion file" + (
                    ": a registration result, read by femreg.load_result (femreg.invert(result) makes an "
                    "inversion of it)" if reg else ""))
            d = {k: z[k] for k in z.files}
        meta = json.loads(str(d["meta"]))
    except FileFormatError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise FileFormatError(f"{path}: unreadable femreg inversion file ({type(exc).__name__}: {exc})") from None
    mesh = (MeshHex1 if d["mesh_points"].shape[0] == 3 else MeshQuad1)(d["mesh_points"], d["mesh_cells"])
    return InversionResult(mesh=mesh, mu=d["mu"], model=meta["model"], lambda_bar=meta["lambda_bar"],
                           beta=meta["beta"], beta_rule=meta.get("beta_rule", ""), sweep=meta.get("sweep", ()),
                           regularization=meta.get("regularization", "tv"),
                           weights=meta.get("weights", DEFAULT_WEIGHTS), u_measured=d["u_measured"],
                           u_model=d["u_model"], strain_measured=d["strain_measured"], misfit=meta["misfit"],
                           regularizer_value=meta["regularizer_value"], history=d["history"],
                           success=meta["success"], message=meta["message"], nit=meta["nit"],
                           timings=meta.get("timings"), model_rule=meta.get("model_rule", ""),
                           mesh_rule=meta.get("mesh_rule", ""), strain_ratio=meta.get("strain_ratio", np.nan),
                           flags=meta.get("flags", ()),
                           uncertainty=d.get("uncertainty"), constrained=d.get("constrained"),
                           shear_modulus_kpa=d.get("shear_modulus_kpa"), reference=meta.get("reference"),
                           one_step=meta.get("one_step"),
                           misfit_model_strain=meta.get("misfit_model_strain", np.nan),
                           lateral_shortfall=meta.get("lateral_shortfall", np.nan),
                           # files written before the check: not assessed (None)
                           uncertainty_calibrated=meta.get("uncertainty_calibrated"), notes=meta.get("notes", ()),
                           unsupported_area=meta.get("unsupported_area", np.nan),
                           uncertainty_scale=meta.get("uncertainty_scale"))


def modulus_contrast(result: InversionResult, inside) -> dict:
    """Contrast and CNR of a modulus image against an inclusion ROI.

    ``inside``: callable (n, 2) mm -> (n,) bool ((n, 3) for a 3D result).  Elements whose nodes are all inside
    form the inclusion set B, all outside the background A; elements cut by the ROI boundary are left out (a
    structured mesh cannot follow a curved edge).  Returns ``contrast`` = mean mu(B) / mean mu(A) (area-weighted), ``CNR`` =
    2 (m_A - m_B)^2 / (s_A^2 + s_B^2) (the paper's CNR_e formula applied to mu), ``cv_background`` = s_A / m_A,
    and ``edge_error_mm``: the largest distance to the ROI boundary of an element whose class, thresholded at
    the geometric mean of the two means, disagrees with its centre's true class (0 if none), with
    ``element_size_mm`` for comparison.
    """
    from skfem import Basis

    mesh = result.mesh
    node_in = np.asarray(inside(mesh.p.T), bool)
    all_in = node_in[mesh.t].all(axis=0)
    all_out = (~node_in[mesh.t]).all(axis=0)
    if not all_in.any() or not all_out.any():
        raise InputError("the ROI leaves no element fully inside or fully outside")
    w = Basis(mesh, _elements(mesh)[1]).dx.sum(axis=1)
    mu = result.mu

    def stats(s):
        m = float(np.sum(w[s] * mu[s]) / np.sum(w[s]))
        return m, float(np.sum(w[s] * (mu[s] - m) ** 2) / np.sum(w[s]))

    mA, vA = stats(all_out)
    mB, vB = stats(all_in)
    c = result.centroids
    c_in = np.asarray(inside(c), bool)
    thr = np.sqrt(mA * mB)
    cls = (mu > thr) if mB > mA else (mu < thr)
    wrong = cls != c_in
    ext = mesh.p[:, mesh.t].max(axis=1) - mesh.p[:, mesh.t].min(axis=1)
    h = float(np.max(ext))
    edge = 0.0
    if wrong.any():
        # distance of a wrong element's centre to the ROI boundary, by bisection along its segment to the
        # nearest element centre of the other class
        dists = []
        for e in np.flatnonzero(wrong):
            opp = np.flatnonzero(c_in != c_in[e])
            if opp.size == 0:
                continue
            q = c[opp[np.argmin(np.sum((c[opp] - c[e]) ** 2, axis=1))]]
            a, b = c[e].copy(), q.copy()
            for _ in range(30):
                m = 0.5 * (a + b)
                if bool(inside(m[None])[0]) == bool(c_in[e]):
                    a = m
                else:
                    b = m
            dists.append(float(np.linalg.norm(c[e] - a)))
        edge = max(dists) if dists else 0.0
    return {"contrast": mB / mA, "CNR": 2.0 * (mA - mB) ** 2 / (vA + vB) if vA + vB > 0 else float("inf"),
            "mean_background": mA, "mean_inclusion": mB, "cv_background": float(np.sqrt(vA) / mA),
            "n_wrong": int(wrong.sum()), "edge_error_mm": edge, "element_size_mm": h}
