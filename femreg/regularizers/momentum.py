r"""Momentum (SPREME) regularisers R_P_eps and R_P_sigma and the total-variation machinery behind them.

Paper (arXiv:2508.19086) section "Regularization Types" (eq:meq to eq:mreg) and appendix "Reduced Form of TV Momentum
Regularization" (eq:Ae5 to eq:Ae7, eq:dmreg to eq:dmreg4).  For a piecewise-homogeneous solid the equilibrium
equation :math:`\nabla\cdot(\mu A[u]) = 0` (eq:meq) with

.. math::  A[u] = \bar\lambda\,(\nabla\cdot u)\,I + 2\,\nabla^s u

reduces to :math:`\nabla\cdot A = 0` almost everywhere (eq:pwcmeq).  On bilinear quads A is taken as piecewise
constant, so :math:`\int_\Omega \|\nabla\cdot A\|` becomes a sum of traction jumps over the interior edges
(eq:Ae7), smoothed by :math:`\delta` (eq:dmreg):

.. math::  \bar R = \alpha \sum_j l_j \sqrt{(K^x_j u)^2 + (K^y_j u)^2 + \delta}          \quad\text{(eq:dmreg2)}

where :math:`K^x_j u, K^y_j u` are the two components of :math:`[\![A]\!]\cdot n` at the midpoint of interior
edge j, each side's A evaluated from its own element.  Gradient eq:dmreg3; Hessian by lagged diffusivity
eq:dmreg4, :math:`\alpha K^T W K` with :math:`W = \mathrm{diag}(l_j / \sqrt{|K_j u|^2 + \delta})`.

Contents
--------
:func:`momentum_jump_operators`
    K^x, K^y, edge lengths for a ``MeshQuad1`` (structured or not), built once per mesh with scikit-fem's
    ``InteriorFacetBasis`` (1-point midpoint rule, both sides).
:class:`TVRegularizer`
    Generic :math:`\alpha\sum_j w_j\,\phi(|K_j u|^2)` for any grouped sparse operator (the momentum terms are two
    instances; :func:`femreg.regularizers.from_operator` builds user ones).

:class:`MomentumRegularizer`, :class:`PlaneStrainMomentumRegularizer` ("momentum-strain", R_P_eps,
:math:`\bar\lambda = 9`, dilatation at the element centre), :class:`PlaneStressMomentumRegularizer`
("momentum-stress", R_P_sigma, :math:`\bar\lambda = 2`).

Kernel
------
On a tensor mesh ``K`` annihilates the 6 affine fields and 4 more fields whatever the mesh size, among them the
two checkerboard (hourglass) modes of bilinear quads: the edge-midpoint jumps of the paper's reduced form cannot
see them, so only the image term controls them (with noisy images a faint mesh-scale pattern can remain in u).
``tests/test_momentum.py::test_kernel_is_affine_plus_four_mesh_modes`` pins this down.

Default alphas
--------------
The defaults are the values selected by the paper's procedure (appendix "Algorithmic Parameter Justification",
``femreg study``) for femreg's normalisation (images divided by the reference RMS, pixel weights dx dy in mm^2,
lengths in mm) on its default 2 mm mesh, shipped in femreg/data/default_alphas.json and applied by
:mod:`femreg.regularizers`: ``momentum-stress`` 0.133, ``momentum-strain`` 0.1 (docs/study_report.md).  The
class attributes ``default_alpha`` below are used only if that file is missing.  The paper's own alphas (2.33e-4,
1.14e-4) belong to its image scaling and do not transfer.

References
----------
* The method (SPREME): momentum-regularised registration, arXiv:2508.19086.
* Total variation: L. I. Rudin, S. Osher, E. Fatemi, Physica D 60:259-268 (1992), doi:10.1016/0167-2789(92)90242-F.
* Lagged diffusivity (eq:dmreg4): C. R. Vogel, M. E. Oman, SIAM J. Sci. Comput. 17(1):227-238 (1996),
  doi:10.1137/0917016.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from .. import _kernels
from ..errors import InputError
from ..material import LAMBDA_BAR_PLANE_STRAIN, LAMBDA_BAR_PLANE_STRESS, lambda_bar

#: :math:`\bar\lambda = 2\nu / (1 - 2\nu)` of the momentum regularisers on volumes (hexahedral meshes), nu = 0.45
#: (nearly incompressible tissue, as R_P_eps: in 3D there is no plane model to choose).
LAMBDA_BAR_3D = 9.0
from ..quadrature import EDGE_MIDPOINT_RULE, ELEMENT_CENTRE_RULE  # noqa: F401  (re-exported)
from .base import Regularizer, register_regularizer

#: Smoothing of the TV norm (eq:dmreg), as in the paper.
DEFAULT_DELTA = 1e-8


def lambda_bar_from_poisson(nu: float, model: str = "plane-strain") -> float:
    r""":math:`\bar\lambda` of eq:cEq for Poisson's ratio ``nu`` (:func:`femreg.material.lambda_bar`)."""
    return lambda_bar(model, nu)


# ----------------------------------------------------------------------------------------------------------
# Jump operators (eq:Ae7 / eq:dmreg2)
# ----------------------------------------------------------------------------------------------------------

@dataclass
class JumpOperators:
    r"""Discrete traction-jump operators of one mesh (appendix eq:dmreg2).

    Attributes
    ----------
    Kx, Ky : (n_edges, 2 n_nodes) csr_matrix
        x and y components of :math:`[\![A]\!]\cdot n` (dimensionless, like strain) at each interior edge
        midpoint, acting on the interleaved nodal displacement (mm; entries in 1/mm).  Jump = side 0 minus
        side 1, n = side-0 outward unit normal.
    lengths : (n_edges,) float
        Edge lengths l_j (mm).
    facets : (n_edges,) int
        Mesh facet index of each row.
    elements : (2, n_edges) int
        Element on side 0 and side 1 of each edge.
    midpoints, normals : (2, n_edges) float
        Edge centres (mm) and side-0 unit normals.
    """

    Kx: sp.csr_matrix
    Ky: sp.csr_matrix
    lengths: np.ndarray
    facets: np.ndarray
    elements: np.ndarray
    midpoints: np.ndarray
    normals: np.ndarray
    #: z component on a hexahedral mesh (faces instead of edges; ``lengths`` are then the face areas, mm^2)
    Kz: sp.csr_matrix | None = None

    @property
    def n_edges(self) -> int:
        return self.lengths.shape[0]

    @property
    def components(self) -> list:
        """[Kx, Ky] in 2D, [Kx, Ky, Kz] in 3D."""
        return [self.Kx, self.Ky] + ([] if self.Kz is None else [self.Kz])

    def stacked(self) -> sp.csr_matrix:
        """``vstack([Kx, Ky(, Kz)])``, shape (dim n_edges, dim n_nodes)."""
        return sp.vstack(self.components, format="csr")


def _check_quad_mesh(mesh) -> None:
    from skfem import MeshHex1, MeshQuad1

    if isinstance(mesh, MeshHex1) and mesh.p.shape[0] == 3:     # a volume's trilinear hexahedra
        return
    if not isinstance(mesh, MeshQuad1):
        raise ValueError(f"momentum regularisers need a scikit-fem MeshQuad1 (bilinear quads), got "
                         f"{type(mesh).__name__}")
    if mesh.p.shape[0] != 2:
        raise ValueError(f"momentum regularisers need a 2D mesh, got mesh.p of shape {mesh.p.shape}")


def momentum_tensor(u, lambda_bar):
    r""":math:`A[u] = \bar\lambda\,(\nabla\cdot u)\,I + 2\,\nabla^s u` (eq:meq), written with ``skfem.helpers``
    for a vector field or basis function ``u`` of a form; shape (2, 2, ...), dimensionless (strain units)."""
    from skfem.helpers import div, eye, sym_grad

    e = sym_grad(u)
    return lambda_bar * eye(div(u), e.shape[0]) + 2.0 * e


def _traction_form(component: int):
    from skfem import LinearForm
    from skfem.helpers import dot

    @LinearForm
    def traction(v, w):
        """Component ``component`` of A[v] n (eq:Ae7): w.lambda_bar, w.n the side-0 unit normal."""
        return dot(momentum_tensor(v, w.lambda_bar), w.n)[component]

    return traction


def _facet_rows(forms, basis, sign, w) -> list:
    """``sign`` x mean over each facet of every LinearForm in ``forms`` on one side's ``basis``: the facets'
    rows as (rows, cols, values) triplets, one per form (scikit-fem elemental assembly)."""
    out = []
    length = basis.dx.sum(axis=1)                                       # (n_facets,) facet lengths
    rows = np.broadcast_to(np.arange(basis.nelems), basis.element_dofs.shape)
    for form in forms:
        local = form.elemental(basis, **w).data.reshape(basis.Nbfun, basis.nelems)
        out.append((rows, basis.element_dofs, sign * local / length))
    return out


def facet_jump_operators(mesh, forms, *, quadrature=EDGE_MIDPOINT_RULE, **w):
    r"""Jump operators of linear weak-form quantities across the interior edges of a quad mesh.

    For each scikit-fem ``LinearForm`` :math:`f_c(v, w)` in ``forms`` (linear in the vector test function v of
    ``ElementVector(ElementQuad1())``), row j of component c maps a nodal displacement u to
    :math:`[\![f_c(u)]\!]_j = \bar f_c(u)|_{\text{side 0}} - \bar f_c(u)|_{\text{side 1}}`, the bar the mean
    over edge j (its value at the midpoint with the default 1-point rule).  ``w.n`` is the side-0 unit normal on
    both sides; extra keyword arguments reach the forms as ``w.<name>`` (numbers as they are, nodal vectors
    interpolated by scikit-fem).  This is how the momentum jumps [[A[u]]] n of eq:Ae7 are built, and how a
    user writes a TV regulariser as a weak form (:func:`femreg.regularizers.from_jump_forms`).

    Returns
    -------
    components : list of (n_edges, 2 n_nodes) csr_matrix
        One per form; entries in the form's units per mm of displacement.
    lengths : (n_edges,) float
        Edge lengths (mm), the weights :math:`l_j` of eq:dmreg2.
    sides : (InteriorFacetBasis, InteriorFacetBasis)
        The two sides' bases (normals, midpoints, elements on each side).
    """
    from skfem import ElementVector, InteriorFacetBasis

    from ..quadrature import for_dimension
    from .base import nodal_element

    _check_quad_mesh(mesh)
    elem = ElementVector(nodal_element(mesh))
    quadrature = for_dimension(quadrature, mesh.p.shape[0])
    sides = tuple(InteriorFacetBasis(mesh, elem, side=s, quadrature=quadrature) for s in (0, 1))
    n_edges, n_dofs = sides[0].nelems, sides[0].N
    trip = [_facet_rows(forms, b, sign, w) for b, sign in zip(sides, (1.0, -1.0))]   # jump = side 0 - side 1
    comps = []
    for c in range(len(forms)):
        r, cc, v = (np.concatenate([np.ravel(t[c][k]) for t in trip]) for k in range(3))
        K = sp.csr_matrix((v, (r, cc)), shape=(n_edges, n_dofs))
        K.sum_duplicates()
        comps.append(K)
    return comps, sides[0].dx.sum(axis=1), sides


def element_centre_divergence(mesh) -> sp.csr_matrix:
    r"""Operator D, shape (n_elements, 2 n_nodes): :math:`(D u)_e = \nabla\cdot u` at the centre of element e.

    The 1-point reduced rule used for the dilatation of R_P_eps (appendix, last paragraph before eq:dmreg2):
    the trace of :func:`femreg.regularizers.centre_gradient_operators`.
    """
    from ..fields import centre_gradient_operators

    _check_quad_mesh(mesh)
    if mesh.p.shape[0] == 3:
        from ..volume_fields import centre_gradients

        G, _ = centre_gradients(mesh)
        return (G[0][0] + G[1][1] + G[2][2]).tocsr()
    G, _ = centre_gradient_operators(mesh)
    return (G["xx"] + G["yy"]).tocsr()


def momentum_jump_operators(mesh, lambda_bar: float, *, dilatation: str = "edge") -> JumpOperators:
    r"""Build K^x, K^y of eq:dmreg2: the components of :math:`[\![A[u]]\!]\cdot n` at interior edge midpoints.

    :math:`A[u]` is :func:`momentum_tensor` (eq:meq), assembled as two ``LinearForm`` s on scikit-fem's
    ``InteriorFacetBasis`` (side 0 and side 1, 1-point midpoint rule, the side-0 normal on both) by
    :func:`facet_jump_operators`; :math:`\bar\lambda` reaches the forms through ``w``.  Call once per mesh.

    Parameters
    ----------
    mesh : skfem.MeshQuad1
        Registration mesh, mm; structured or not.
    lambda_bar : float
        :math:`\bar\lambda` (9 for R_P_eps, 2 for R_P_sigma).
    dilatation : {"edge", "centre"}
        Where :math:`\nabla\cdot u` of the :math:`\bar\lambda` term is evaluated: at the edge midpoint like the
        rest of A ("edge", R_P_sigma) or at each element's centre ("centre", reduced integration against
        locking, R_P_eps): :math:`[\![A]\!] n = [\![2\nabla^s u]\!] n + \bar\lambda [\![\nabla\cdot
        u(\text{centre})]\!] n`.

    Returns
    -------
    JumpOperators
    """
    _check_quad_mesh(mesh)
    lambda_bar = float(lambda_bar)
    if not np.isfinite(lambda_bar) or lambda_bar < 0:
        raise ValueError(f"lambda_bar must be a finite number >= 0, got {lambda_bar!r}")
    if dilatation not in ("edge", "centre", "center"):
        raise ValueError(f"dilatation must be 'edge' or 'centre', got {dilatation!r}")
    centre = dilatation in ("centre", "center")
    lb_edge = 0.0 if centre else lambda_bar

    from ..mesh import tensor_structure

    dim = mesh.p.shape[0]
    Kz = None
    ts = tensor_structure(mesh) if dim == 2 else None
    if ts is not None:
        Kx, Ky, lengths, facets, tind, mid, n = _tensor_traction_jumps(mesh, ts, lb_edge,
                                                                       lambda_bar if centre else 0.0)
        centre = False                  # already in
    else:
        comps, lengths, sides = facet_jump_operators(mesh, [_traction_form(c) for c in range(dim)],
                                                     lambda_bar=lb_edge)
        Kx, Ky = comps[:2]
        Kz = comps[2] if dim == 3 else None
        b0 = sides[0]
        n = np.asarray(b0.normals)[:, :, 0].copy()      # (dim, n_edges) side-0 unit normal
        facets, tind = np.asarray(b0.find).copy(), np.stack([sides[0].tind, sides[1].tind])
        mid = np.asarray(b0.global_coordinates())[:, :, 0].copy()
    if centre and lambda_bar != 0.0:
        # lambda_bar [[div u(centre)]] n: each side element's centre divergence, carried to its edges
        D = element_centre_divergence(mesh)
        Dj = (D[tind[0]] - D[tind[1]]) * lambda_bar
        Kx = (Kx + sp.diags(n[0]) @ Dj).tocsr()
        Ky = (Ky + sp.diags(n[1]) @ Dj).tocsr()
        if Kz is not None:
            Kz = (Kz + sp.diags(n[2]) @ Dj).tocsr()
    return JumpOperators(Kx=Kx, Ky=Ky, lengths=lengths, facets=facets, elements=tind, midpoints=mid, normals=n,
                         Kz=Kz)


def _rectangle_side(mid, x0, x1, y0) -> np.ndarray:
    """Which edge of an axis-aligned rectangle [x0, x1] x [y0, y1] each midpoint ``mid`` (2, n) lies on:
    0 x = x0, 1 x = x1, 2 y = y0, 3 y = y1 (the order of :func:`_edge_tractions`)."""
    return np.where(np.isclose(mid[0], x0), 0, np.where(np.isclose(mid[0], x1), 1,
                                                        np.where(np.isclose(mid[1], y0), 2, 3)))


def _edge_tractions(lambda_bar: float, hx: float, hy: float) -> np.ndarray:
    """Outward traction A[N] n (:func:`_traction_form`) at the midpoint of each edge of one hx x hy rectangle,
    from scikit-fem on a one-element mesh: (2 components, 4 edges x-, x+, y-, y+, 4 corners (0,0) (1,0) (1,1)
    (0,1) in (x, y) steps, 2 displacement components), per mm."""
    from skfem import ElementQuad1, ElementVector, FacetBasis, MeshQuad1

    p = np.array([[0.0, hx, hx, 0.0], [0.0, 0.0, hy, hy]])
    m = MeshQuad1(p, np.array([[0], [1], [2], [3]]))
    b = FacetBasis(m, ElementVector(ElementQuad1()), quadrature=EDGE_MIDPOINT_RULE)
    rows = _facet_rows([_traction_form(0), _traction_form(1)], b, 1.0, {"n": b.normals, "lambda_bar": lambda_bar})
    mid = m.p[:, m.facets[:, b.find]].mean(axis=1)                     # (2, 4) edge midpoints
    side = _rectangle_side(mid, 0.0, hx, 0.0)
    node_of_dof = np.empty(b.N, int)
    comp_of_dof = np.empty(b.N, int)
    for c in range(2):
        node_of_dof[b.nodal_dofs[c]] = np.arange(m.p.shape[1])
        comp_of_dof[b.nodal_dofs[c]] = c
    out = np.zeros((2, 4, 4, 2))
    for k, (_, cols, vals) in enumerate(rows):
        for f in range(b.nelems):
            out[k, side[f], node_of_dof[cols[:, f]], comp_of_dof[cols[:, f]]] = vals[:, f]
    return out


@functools.lru_cache(maxsize=16)
def _traction_parts(lambda_bar: float):
    """(A, B) with :func:`_edge_tractions` (hx, hy) = A / hx + B / hy (read-only; constants of the form, so
    computed once per lambda_bar and process)."""
    T11, T12 = _edge_tractions(lambda_bar, 1.0, 1.0), _edge_tractions(lambda_bar, 1.0, 2.0)
    B = 2.0 * (T11 - T12)                        # the 1/hy part
    A = T11 - B                                  # the 1/hx part
    A.flags.writeable = B.flags.writeable = False
    return A, B


def _tensor_traction_jumps(mesh, ts, lambda_bar: float, centre_lambda: float = 0.0):
    """The jump operators of :func:`momentum_jump_operators` on an axis-aligned tensor mesh, the same
    rows in the same order as scikit-fem's ``InteriorFacetBasis`` gives them (interior facets in index order,
    side 0 = ``mesh.f2t[0]``).  Each edge's row is the outward traction of both elements at the edge midpoint
    (jump with the side-0 normal = side 0's outward traction + side 1's), taken from :func:`_edge_tractions`:
    on a rectangle the traction is linear in 1/hx and 1/hy, so two one-element evaluations by scikit-fem give
    it for every element size.  Why not ``InteriorFacetBasis`` here: its set-up per mesh costs more, and a
    registration builds two meshes; this reuses the form's constants.
    ``lambda_bar`` weighs the dilatation at the edge midpoint; ``centre_lambda`` the jump of the element-centre
    dilatation times the side-0 normal (the centre form of :func:`momentum_jump_operators`), added to the same
    entries (the centre gradients of :func:`femreg.regularizers.centre_gradient_operators`)."""
    from ..mesh import tensor_node_grid

    from ..fields import _unit_centre_gradients

    xs, ys, cell = ts
    A, B = _traction_parts(float(lambda_bar))
    V = _unit_centre_gradients()
    n_el = mesh.t.shape[1]
    ci, cj = np.empty(n_el, int), np.empty(n_el, int)
    I, J = np.meshgrid(np.arange(cell.shape[0]), np.arange(cell.shape[1]), indexing="ij")
    ci[cell.ravel()], cj[cell.ravel()] = I.ravel(), J.ravel()
    node = tensor_node_grid(mesh, xs, ys)
    f2t = mesh.f2t
    facets = np.nonzero(f2t[1] != -1)[0].astype(np.int32)
    tind = np.stack([f2t[0, facets], f2t[1, facets]])
    fp = mesh.p[:, mesh.facets[:, facets]]                          # (2, 2 ends, n_edges)
    mid = fp.mean(axis=1)
    lengths = np.hypot(*(fp[:, 1] - fp[:, 0]))
    a_steps = np.array([0, 1, 1, 0])
    b_steps = np.array([0, 0, 1, 1])
    rows_all, cols_all, vals_all = [], [[], []], [[], []]
    normals = None
    for s in (0, 1):
        e = tind[s]
        i, j = ci[e], cj[e]
        hx, hy = xs[i + 1] - xs[i], ys[j + 1] - ys[j]
        side = _rectangle_side(mid, xs[i], xs[i + 1], ys[j])
        if s == 0:   # side-0 outward unit normal
            normals = np.stack([np.select([side == 0, side == 1], [-1.0, 1.0], 0.0),
                                np.select([side == 2, side == 3], [-1.0, 1.0], 0.0)])
        vals = A[:, side] / hx[None, :, None, None] + B[:, side] / hy[None, :, None, None]   # (2, n_e, 4, 2)
        if centre_lambda != 0.0:      # +- lambda [div u(centre of this side's element)] n, side 0 minus side 1
            div = np.stack([V[None, :, 0] / hx[:, None], V[None, :, 1] / hy[:, None]], axis=-1)   # (n_e, 4, 2)
            sign = centre_lambda if s == 0 else -centre_lambda
            vals = vals + sign * normals[:, :, None, None] * div[None]
        nodes = node[i[:, None] + a_steps[None, :], j[:, None] + b_steps[None, :]]          # (n_e, 4)
        cols = (2 * nodes[:, :, None] + np.arange(2)[None, None, :])                        # (n_e, 4, 2)
        rows_all.append(np.broadcast_to(np.arange(facets.size)[:, None, None], cols.shape).ravel())
        for k in range(2):
            cols_all[k].append(cols.ravel())
            vals_all[k].append(vals[k].ravel())
    shape = (facets.size, 2 * mesh.p.shape[1])
    rows = np.concatenate(rows_all)
    K = []
    for k in range(2):
        M = sp.csr_matrix((np.concatenate(vals_all[k]), (rows, np.concatenate(cols_all[k]))), shape=shape)
        M.sum_duplicates()
        M.eliminate_zeros()          # structural zeros (a normal component or a traction term that is 0)
        K.append(M)
    return K[0], K[1], lengths, facets, tind, mid, normals


def hourglass_operator(mesh) -> sp.csr_matrix:
    r"""Hourglass operator G, shape (2 n_elements, 2 n_nodes): row e (row n_el + e) gives
    :math:`u_0 - u_1 + u_2 - u_3` of the x (y) displacement over the corners of quad e, in order around it.

    It vanishes for affine fields and picks out the node-to-node checkerboard mode of bilinear quads, which the
    edge-midpoint jumps of eq:Ae7 cannot see.  Used by the optional hourglass control of
    :class:`MomentumRegularizer` and by :func:`femreg.quality.hourglass`.
    """
    t = np.asarray(mesh.t)
    if t.shape[0] == 8 and mesh.p.shape[0] == 3:
        return _hex_hourglass_operator(mesh)
    if t.shape[0] != 4:
        raise InputError(f"hourglass operator needs quadrilateral elements, got {t.shape[0]} nodes per element")
    n_el = t.shape[1]
    rows = np.repeat(np.arange(2 * n_el), 4)
    cols = np.concatenate([2 * t.T, 2 * t.T + 1]).ravel()
    vals = np.tile([1.0, -1.0, 1.0, -1.0], 2 * n_el)
    return sp.csr_matrix((vals, (rows, cols)), shape=(2 * n_el, 2 * mesh.p.shape[1]))


def _hex_hourglass_operator(mesh) -> sp.csr_matrix:
    r"""The hexahedral form of :func:`hourglass_operator`, shape (12 n_elements, 3 n_nodes): per element and
    displacement component the four hourglass vectors :math:`s_x s_y, s_x s_z, s_y s_z, s_x s_y s_z` over its 8
    corners (:math:`s = \pm 1` the corner's side along each reference axis, from ``ElementHex1``'s nodes).
    On a box they are orthogonal to every affine field and span the trilinear modes the face-centre jumps cannot
    see (Flanagan & Belytschko, Int. J. Numer. Meth. Eng. 17:679-706, 1981)."""
    from skfem import ElementHex1

    s = 2.0 * np.asarray(ElementHex1().doflocs, float).T - 1.0              # (3, 8) corner sides
    modes = np.stack([s[0] * s[1], s[0] * s[2], s[1] * s[2], s[0] * s[1] * s[2]])   # (4, 8)
    t = np.asarray(mesh.t)
    n_el = t.shape[1]
    rows, cols, vals = [], [], []
    for c in range(3):
        for k in range(4):
            r = (c * 4 + k) * n_el + np.arange(n_el)
            rows.append(np.repeat(r, 8))
            cols.append((3 * t.T + c).ravel())
            vals.append(np.tile(modes[k], n_el))
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(12 * n_el, 3 * mesh.p.shape[1]))


# ----------------------------------------------------------------------------------------------------------
# Generic total-variation-type regulariser (eq:dmreg2 to eq:dmreg4)
# ----------------------------------------------------------------------------------------------------------

def _penalty_functions(penalty, delta: float):
    """Return (phi, dphi) of s = |K_j u|^2 for a named penalty or a user pair of callables."""
    if isinstance(penalty, tuple):
        if len(penalty) != 2 or not all(map(callable, penalty)):
            raise ValueError("a custom penalty must be a pair (phi, dphi) of callables of s = |K_j u|^2 "
                             "(dphi = d phi / d s >= 0)")
        return penalty
    if penalty == "tv":
        # eq:dmreg: sqrt(s + delta); d/ds = 1 / (2 sqrt(s + delta))
        return (lambda s: np.sqrt(s + delta)), (lambda s: 0.5 / np.sqrt(s + delta))
    if penalty == "quadratic":
        return (lambda s: 0.5 * s), (lambda s: np.full_like(s, 0.5))
    if penalty == "huber":
        # quadratic below sqrt(delta), linear above: a TV variant without the sqrt(delta) floor
        eps = np.sqrt(delta)

        def phi(s):
            r = np.sqrt(s)
            return np.where(r <= eps, 0.5 * s / eps, r - 0.5 * eps)

        def dphi(s):
            r = np.sqrt(s)
            return np.where(r <= eps, 0.5 / eps, 0.5 / np.maximum(r, eps))
        return phi, dphi
    raise ValueError(f"penalty must be 'tv', 'huber', 'quadratic' or a pair (phi, dphi) of callables, "
                     f"got {penalty!r}")


class TVRegularizer(Regularizer):
    r""":math:`R[u] = \alpha \sum_j w_j\, \phi(|K_j u|^2)`, with :math:`K_j u \in \mathbb{R}^m` one term.

    With the default ``penalty="tv"``, :math:`\phi(s) = \sqrt{s + \delta}` and this is eq:dmreg2; the gradient is
    eq:dmreg3, :math:`\alpha \sum_c K_c^T (2 w \phi'(s) \odot K_c u)`, and ``hessian`` is the lagged-diffusivity
    approximation eq:dmreg4, :math:`\alpha \sum_c K_c^T \mathrm{diag}(2 w \phi'(s)) K_c` (symmetric PSD for
    :math:`\phi' \ge 0`; the :math:`g\otimes g` term of the exact Hessian is dropped).

    Parameters
    ----------
    operator : callable
        ``operator(mesh) -> (components, weights)``: ``components`` a sequence of m sparse matrices
        ``K_c`` of shape (n_terms, 2 n_nodes) (row j of every component belongs to term j; a single sparse
        matrix means m = 1), ``weights`` (n_terms,) nonnegative (e.g. edge lengths l_j or element areas).
        Called once per mesh in :meth:`setup`.
    alpha : float
        :math:`\alpha`.
    delta : float
        Smoothing :math:`\delta` > 0 of the TV norm (eq:dmreg), in the units of :math:`|K_j u|^2`.
    penalty : "tv", "huber", "quadratic" or (phi, dphi)
        :math:`\phi(s)` of the squared term norm s and its derivative :math:`d\phi/ds \ge 0`, both vectorised.
    name : str
        Label in results and reports.
    """

    quadratic = False

    def __init__(self, operator: Callable | None = None, alpha: float | None = None, *,
                 delta: float = DEFAULT_DELTA, penalty="tv", name: str = "custom-tv"):
        super().__init__(alpha)
        delta = float(delta)
        if not np.isfinite(delta) or delta <= 0:
            raise ValueError(f"delta must be a finite number > 0, got {delta!r}")
        self.delta = delta
        self.penalty = penalty
        self._phi, self._dphi = _penalty_functions(penalty, delta)
        if operator is not None and not callable(operator):
            raise ValueError(f"operator must be a callable mesh -> (components, weights), got {operator!r}")
        self._operator = operator
        self.name = name
        self._K = None            # stacked (m * n_terms, ndof) csr
        self._KT = None
        self._weights = None
        self._m = 0
        self._cache = (None, None)
        self._gram = None

    # -- construction ---------------------------------------------------------------------------------------
    def build_operator(self, mesh):
        """Return ``(components, weights)`` for ``mesh``; subclasses may override instead of passing ``operator``."""
        if self._operator is None:
            raise ValueError(f"{type(self).__name__} needs an operator(mesh) -> (components, weights)")
        return self._operator(mesh)

    def setup(self, mesh) -> None:
        out = self.build_operator(mesh)
        if not (isinstance(out, tuple) and len(out) == 2):
            raise ValueError("operator(mesh) must return (components, weights)")
        comps, weights = out
        if sp.issparse(comps) or isinstance(comps, np.ndarray):
            comps = [comps]
        comps = [sp.csr_matrix(c) for c in comps]
        if not comps:
            raise ValueError("operator(mesh) returned no components")
        n_terms, n_dofs = comps[0].shape
        if any(c.shape != (n_terms, n_dofs) for c in comps):
            raise ValueError(f"all operator components must have the same shape; got {[c.shape for c in comps]}")
        dim = mesh.p.shape[0]
        expected = dim * mesh.p.shape[1]
        if n_dofs != expected:
            raise ValueError(f"operator components must have {dim} * n_nodes = {expected} columns, got {n_dofs}")
        weights = np.asarray(weights, dtype=float).ravel()
        if weights.shape != (n_terms,):
            raise ValueError(f"weights must have shape ({n_terms},), got {weights.shape}")
        if not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("weights must be finite and >= 0")
        self._m = len(comps)
        self._K = sp.vstack(comps, format="csr")
        self._K.sort_indices()
        self._KT = self._K.T.tocsr()
        self._weights = weights
        self._cache = (None, None)
        self._gram = None
        self.mesh = mesh

    # -- evaluation -----------------------------------------------------------------------------------------
    @property
    def operator(self) -> sp.csr_matrix:
        """Stacked operator ``vstack(components)``, shape (m n_terms, 2 n_nodes)."""
        if self._K is None:
            raise RuntimeError("call setup(mesh) first")
        return self._K

    @property
    def weights(self) -> np.ndarray:
        if self._weights is None:
            raise RuntimeError("call setup(mesh) first")
        return self._weights

    def term_values(self, u: np.ndarray) -> np.ndarray:
        """K_j u for every term, shape (m, n_terms)."""
        u = np.asarray(u, dtype=float)
        if u.shape != (self.operator.shape[1],):
            raise ValueError(f"u must have shape ({self.operator.shape[1]},), got {u.shape}")
        key, val = self._cache
        if key is not None and key.shape == u.shape and np.array_equal(key, u):
            return val
        val = (self._K @ u).reshape(self._m, -1)
        self._cache = (u.copy(), val)
        return val

    def term_norms(self, u: np.ndarray) -> np.ndarray:
        """``|K_j u|`` per term (e.g. ``|[[A]]·n|`` per edge, dimensionless), shape (n_terms,)."""
        return np.sqrt(np.sum(self.term_values(u) ** 2, axis=0))

    def diffusivity(self, u: np.ndarray) -> np.ndarray:
        r"""Lagged diffusivity :math:`2 w_j \phi'(s_j)` (eq:dmreg4: :math:`l_j/\sqrt{|K_j u|^2+\delta}`)."""
        s = np.sum(self.term_values(u) ** 2, axis=0)
        return 2.0 * self._weights * self._dphi(s)

    def energy(self, u):
        s = np.sum(self.term_values(u) ** 2, axis=0)
        return self.alpha * float(self._weights @ self._phi(s))

    def gradient(self, u):
        Ku = self.term_values(u)
        d = self.diffusivity(u)
        return self.alpha * (self._KT @ (Ku * d).ravel())

    def constant_hessian(self):
        """Constant part of the Hessian without alpha (sparse, 2 n_nodes square) or None; subclasses with a
        quadratic term add it here (energy ``alpha/2 u^T Q u``)."""
        return None

    def hessian(self, u):
        return self.hessian_plus(u)

    def hessian_plus(self, u, C=None):
        """``alpha K^T diag(d) K + alpha Q + C`` (eq:dmreg4, Q the :meth:`constant_hessian`, C e.g. the fixed
        data Hessian of eq:wfnew) as a symmetric CSC matrix.

        With the compiled kernels the sum lands in a pattern fixed per mesh, alpha and C (a Gustavson product
        into it, cheaper than scipy's product plus the sums), so the linear
        solver also reuses its band layout."""
        dd = np.tile(self.diffusivity(u), self._m)     # row weights of the stacked operator
        Q = self.constant_hessian()
        if not _kernels.use_compiled():
            H = self._KT @ (sp.diags(self.alpha * dd) @ self._K)
            if Q is not None:
                H = H + self.alpha * Q
            if C is not None:
                H = H + C
            return sp.csc_matrix(H)
        g = self._gram
        if g is None or g[0] is not self._K or g[1] != self.alpha or g[2] is not C:
            self._gram = g = (self._K, self.alpha, C) + self._gram_pattern(Q, C)
        Hp, Hi, base, marker = g[3:]
        K, KT = self._K, self._KT
        out = _kernels.gram_into_pattern(K.indptr, K.indices, K.data, KT.indptr, KT.indices, KT.data,
                                         self.alpha * dd, Hp, Hi, base, marker, np.empty(base.shape))
        n = K.shape[1]
        # the pattern and the values are symmetric: the CSR arrays are also the CSC ones
        return sp.csc_matrix((out, Hi, Hp), shape=(n, n))

    def _gram_pattern(self, Q, C):
        """(indptr, indices, base values, scratch) of the pattern of K^T K + Q + C, base = alpha Q + C."""
        n = self._K.shape[1]
        absK = abs(self._K)
        P = absK.T @ absK                             # positive entries: no cancellation hides a position
        parts = [(c, s) for c, s in ((Q, self.alpha), (C, 1.0)) if c is not None]
        for c, _ in parts:
            P = P + abs(sp.csr_matrix(c))
        P = sp.csr_matrix(P)
        P.sum_duplicates()
        P.sort_indices()
        Hp, Hi = P.indptr.astype(np.int64), P.indices.astype(np.int64)
        marker = np.zeros(n, dtype=np.int64)
        base = np.zeros(P.nnz)
        for c, s in parts:
            c = sp.csr_matrix(c)
            _kernels.add_into_pattern(c.indptr.astype(np.int64), c.indices.astype(np.int64),
                                      np.asarray(c.data, float), float(s), Hp, Hi, marker, base)
        return Hp, Hi, base, marker


# ----------------------------------------------------------------------------------------------------------
# The momentum regularisers
# ----------------------------------------------------------------------------------------------------------

class MomentumRegularizer(TVRegularizer):
    r"""SPREME momentum regulariser :math:`\alpha\sum_j l_j\sqrt{|[\![A]\!]\cdot n|_j^2 + \delta}` (eq:dmreg2).

    Parameters
    ----------
    alpha : float or None
        :math:`\alpha_{Pm}`; None takes ``default_alpha``.
    lambda_bar : float
        :math:`\bar\lambda` of A (eq:meq).
    delta : float
        :math:`\delta` of eq:dmreg (dimensionless, squared-strain units), 1e-8 as in the paper.
    dilatation : {"edge", "centre"}
        Where the :math:`\bar\lambda\nabla\cdot u` part of A is evaluated (see :func:`momentum_jump_operators`).
    hourglass : float
        Weight (relative to alpha) of an optional hourglass control, not in the paper:
        ``alpha * hourglass / 8 * sum_e sum_c (u_0 - u_1 + u_2 - u_3)_{e,c}^2`` over the corners of each element.
        The edge-midpoint jumps of eq:Ae7 do not see the node-to-node checkerboard ("hourglass") modes of bilinear
        quads, so on real data they can show up in the lateral field; a small weight (e.g. 1) removes them
        while leaving affine fields free.  0 (default) is the paper's regulariser.
    shear_traction : float
        Weight ``w`` of the tangential part of the traction jump, not in the paper: the penalty of edge j becomes
        :math:`\sqrt{(n\cdot[\![A]\!]n)^2 + w^2 (t\cdot[\![A]\!]n)^2 + \delta}` (``t`` the edge tangent;
        rotation invariant).  1 (default) is eq:dmreg2 (the same norm, the operators untouched).  Below 1 a layer
        may slide over another (a jump of the shear traction across the band's faces) at a lower price, while the
        normal traction (compression, inclusions) is held as before.  A callable ``w(jumps)`` (the
        :class:`JumpOperators`) gives one weight per edge (the slip region of :mod:`femreg.refine`).
    normal_traction : float or callable
        Weight of the normal part ``n . [[A]] n`` in the same norm, not in the paper (1: eq:dmreg2); a callable
        ``w(jumps)`` gives one weight per edge (the relaxed edges of :mod:`femreg.refine`: where a bonded
        interface makes ``A n`` jump by the modulus ratio).
    """

    name = "momentum"
    default_alpha = 0.1
    default_lambda_bar = LAMBDA_BAR_PLANE_STRESS
    default_dilatation = "edge"

    def __init__(self, alpha: float | None = None, *, lambda_bar: float | None = None,
                 delta: float = DEFAULT_DELTA, dilatation: str | None = None, hourglass: float = 0.0,
                 shear_traction: float = 1.0, normal_traction: float = 1.0):
        super().__init__(None, alpha, delta=delta, penalty="tv", name=self.name)
        self.shear_traction = shear_traction if callable(shear_traction) else float(shear_traction)
        if not callable(shear_traction) and (not np.isfinite(self.shear_traction) or self.shear_traction <= 0):
            raise ValueError(f"shear_traction must be a finite number > 0, got {shear_traction!r}")
        self.normal_traction = normal_traction if callable(normal_traction) else float(normal_traction)
        if not callable(normal_traction) and (not np.isfinite(self.normal_traction) or self.normal_traction <= 0):
            raise ValueError(f"normal_traction must be a finite number > 0, got {normal_traction!r}")
        self.hourglass = float(hourglass)
        if not np.isfinite(self.hourglass) or self.hourglass < 0:
            raise ValueError(f"hourglass must be a finite number >= 0, got {hourglass!r}")
        self._G = None
        self.lambda_bar = float(self.default_lambda_bar if lambda_bar is None else lambda_bar)
        if not np.isfinite(self.lambda_bar) or self.lambda_bar < 0:
            raise ValueError(f"lambda_bar must be a finite number >= 0, got {lambda_bar!r}")
        self.dilatation = self.default_dilatation if dilatation is None else dilatation
        if self.dilatation not in ("edge", "centre", "center"):
            raise ValueError(f"dilatation must be 'edge' or 'centre', got {dilatation!r}")
        self.jumps: JumpOperators | None = None
        self._lambda_given = lambda_bar is not None
        self._dilatation_given = dilatation is not None

    def build_operator(self, mesh):
        lb, dil = self.lambda_bar, self.dilatation
        if mesh.p.shape[0] == 3:
            # a volume: no plane model; the 3D nearly incompressible A (LAMBDA_BAR_3D) with the dilatation at the
            # element centre (reduced integration of the volumetric part, against locking), unless given
            lb = lb if self._lambda_given else LAMBDA_BAR_3D
            dil = dil if self._dilatation_given else "centre"
        self.jumps = momentum_jump_operators(mesh, lb, dilatation=dil)

        def per_edge(w):                # a callable: one weight per edge, w(jumps) -> (n_edges,) (femreg.refine)
            return sp.diags(np.asarray(w(self.jumps), float)) if callable(w) else w

        w, wn = per_edge(self.shear_traction), per_edge(self.normal_traction)
        if not sp.issparse(w) and not sp.issparse(wn) and w == 1.0 and wn == 1.0:
            if mesh.p.shape[0] == 3:
                return self.jumps.components, self.jumps.lengths
            return [self.jumps.Kx, self.jumps.Ky], self.jumps.lengths

        def scaled(w, K):
            return (w @ K if sp.issparse(w) else w * K).tocsr()

        if mesh.p.shape[0] == 3:
            comps = self.jumps.components
            n = [sp.diags(c) for c in self.jumps.normals]
            Kn = sum(n[c] @ comps[c] for c in range(3)).tocsr()
            tang = [scaled(w, comps[c] - n[c] @ Kn) for c in range(3)]
            return [scaled(wn, Kn)] + tang, self.jumps.lengths
        # normal and tangential components of the jump vector (a rotation of (Kx, Ky) per edge)
        nx, ny = (sp.diags(c) for c in self.jumps.normals)
        Kn = (nx @ self.jumps.Kx + ny @ self.jumps.Ky).tocsr()
        Kt = (nx @ self.jumps.Ky - ny @ self.jumps.Kx).tocsr()
        return [scaled(wn, Kn), scaled(w, Kt)], self.jumps.lengths

    def setup(self, mesh) -> None:
        super().setup(mesh)
        self._G = None
        if self.hourglass > 0:
            G = hourglass_operator(mesh)
            # energy alpha/2 u^T G u; normalised by the corners per element (4 quads, 8 hexahedra)
            self._G = (G.T @ G).tocsr() * (self.hourglass / float(mesh.t.shape[0]))

    def energy(self, u):
        e = super().energy(u)
        return e if self._G is None else e + 0.5 * self.alpha * float(u @ (self._G @ u))

    def gradient(self, u):
        g = super().gradient(u)
        return g if self._G is None else g + self.alpha * (self._G @ u)

    def constant_hessian(self):
        return self._G

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(alpha={self.alpha:g}, lambda_bar={self.lambda_bar:g}, "
                f"delta={self.delta:g}, dilatation={self.dilatation!r}, hourglass={self.hourglass:g}"
                + ("" if callable(self.shear_traction) or self.shear_traction == 1.0
                   else f", shear_traction={self.shear_traction:g}")
                + ("" if callable(self.normal_traction) or self.normal_traction == 1.0
                   else f", normal_traction={self.normal_traction:g}") + ")")


class PlaneStrainMomentumRegularizer(MomentumRegularizer):
    r"""R_P_eps: plane strain, :math:`\bar\lambda = 9` (nu = 0.45), dilatation at the element centre."""

    name = "momentum-strain"
    default_alpha = 0.1          # fallback; the shipped default comes from femreg/data/default_alphas.json
    default_lambda_bar = LAMBDA_BAR_PLANE_STRAIN
    default_dilatation = "centre"


class PlaneStressMomentumRegularizer(MomentumRegularizer):
    r"""R_P_sigma: incompressible plane stress, :math:`\bar\lambda = 2`, all of A at the edge midpoint."""

    name = "momentum-stress"
    default_alpha = 0.133        # fallback; the shipped default comes from femreg/data/default_alphas.json
    default_lambda_bar = LAMBDA_BAR_PLANE_STRESS
    default_dilatation = "edge"


register_regularizer(PlaneStrainMomentumRegularizer.name, PlaneStrainMomentumRegularizer)
register_regularizer(PlaneStressMomentumRegularizer.name, PlaneStressMomentumRegularizer)
