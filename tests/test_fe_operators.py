"""The two operators of fe_node.operators implement the forms of fe_node.forms (1e-12 on random weights)."""
import numpy as np
import pytest
import scipy.sparse as sp
from skfem import Basis, ElementHex1, FacetBasis, MeshTet

from fe_node.forms import conduction, conduction_z, facet_area, laser, mass
from fe_node.mesh import Grid, graded_axis
from fe_node.operators import CsrOperator, TensorOperator, box_stiffness
from fe_node.source import surface_load


def small_grid(h=30e-6):
    ax = dict(h=h, growth=1.4, h_max=0.2e-3)
    return Grid(graded_axis(-0.4e-3, 0.5e-3, -0.1e-3, 0.2e-3, **ax),
                graded_axis(-0.3e-3, 0.3e-3, -0.1e-3, 0.1e-3, **ax),
                graded_axis(-0.4e-3, 0.0, -0.1e-3, 0.0, **ax))


@pytest.fixture(scope="module")
def setup():
    g = small_grid()
    mesh, perm = g.skfem_mesh()
    return g, mesh, perm, g.element_order(mesh), Basis(mesh, ElementHex1(), intorder=2)


def skfem_reference(basis, kw, rho_w):
    """K_w and lumped m assembled directly from the forms (skfem element order weights)."""
    nqp = basis.X.shape[-1]
    k = conduction.assemble(basis, kw=np.repeat(kw[:, None], nqp, axis=1))
    m = np.asarray(mass.assemble(basis, rho_w=np.repeat(rho_w[:, None], nqp, axis=1)).sum(axis=1)).ravel()
    return k, m


def close(a, b, tol=1e-12):
    return np.max(np.abs(a - b)) <= tol * np.max(np.abs(b))


@pytest.mark.parametrize("layered", [False, True])
def test_operators_equal_forms_on_random_weights(setup, layered):
    g, mesh, perm, eorder, basis = setup
    rng = np.random.default_rng(3)
    shape = (len(g.ys) - 1, len(g.zs) - 1, len(g.xs) - 1)
    if layered:      # powder-like: weights per z layer, a few elements differing (the tensor path's fast case)
        kw = np.broadcast_to(rng.uniform(0.01, 1.0, shape[1])[None, :, None], shape).copy()
        rho_w = np.broadcast_to(rng.uniform(0.5, 1.0, shape[1])[None, :, None], shape).copy()
        few = rng.choice(kw.size, 40, replace=False)
        kw.ravel()[few], rho_w.ravel()[few] = 1.0, 0.7
    else:
        kw, rho_w = rng.uniform(0.01, 2.0, shape), rng.uniform(0.3, 1.0, shape)
    kw, rho_w = kw.ravel(), rho_w.ravel()
    sk_kw, sk_rho = np.empty_like(kw), np.empty_like(rho_w)
    sk_kw[eorder], sk_rho[eorder] = kw, rho_w
    k_ref, m_ref = skfem_reference(basis, sk_kw, sk_rho)
    k_ref, m_ref = k_ref[perm][:, perm], m_ref[perm]
    nqp = basis.X.shape[-1]
    kz_ref = conduction_z.assemble(basis, kw=np.repeat(sk_kw[:, None], nqp, axis=1))[perm][:, perm]
    u = rng.standard_normal(g.n_nodes)
    tensor = TensorOperator(g, kw, rho_w, vertical=True)
    csr = CsrOperator(mesh, sk_kw, sk_rho, order=perm, vertical=True)
    for op in (tensor, csr):
        assert close(op(u.reshape(g.solver_shape)).ravel(), k_ref @ u)
        assert close(op.vertical(u.reshape(g.solver_shape)).ravel(), kz_ref @ u)
        assert close(np.ravel(op.lumped_mass), m_ref)
    assert abs(tensor.assembled() - k_ref).max() <= 1e-12 * abs(k_ref).max()
    assert tensor.stability_eigenvalue() == pytest.approx(csr.stability_eigenvalue(), rel=1e-9)


def test_reweight_equals_fresh_operator(setup):
    g, mesh, perm, eorder, _ = setup
    rng = np.random.default_rng(4)
    n = eorder.size
    el = rng.choice(n, 300, replace=False)
    kw, rho_w = np.ones(n), np.ones(n)
    kw[el], rho_w[el] = rng.uniform(0.05, 3.0, el.size), rng.uniform(0.4, 1.0, el.size)
    sk = np.empty(n, dtype=np.intp)
    sk[eorder] = np.arange(n)       # skfem element of each solver element
    u = rng.standard_normal(g.n_nodes)
    fresh = TensorOperator(g, kw, rho_w, vertical=True)
    t, c = TensorOperator(g, vertical=True), CsrOperator(mesh, order=perm, vertical=True)
    lam0 = t.stability_eigenvalue()
    t.reweight(el, kw[el], rho_w[el])
    c.reweight(eorder[el], kw[el], rho_w[el])
    for op in (t, c):
        assert close(op(u), fresh(u)) and close(np.ravel(op.lumped_mass), np.ravel(fresh.lumped_mass))
        assert close(op.vertical(u), fresh.vertical(u))
        assert op.stability_eigenvalue() == pytest.approx(fresh.stability_eigenvalue(), rel=1e-9)
    assert t.stability_eigenvalue() > lam0        # the limit follows the weights


def test_vertical_weights_equal_the_forms(setup):
    """Elements with their own vertical weight ``kw_z`` (a coarse element over an insulating powder
    row): ``K = sum_e kw (conduction - conduction_z) + kw_z conduction_z``, built fresh or re-weighted."""
    g, mesh, perm, eorder, basis = setup
    rng = np.random.default_rng(9)
    n, nqp = eorder.size, basis.X.shape[-1]
    kw = np.ones(n)
    el = rng.choice(n, 200, replace=False)
    kw[el] = rng.uniform(0.3, 1.0, el.size)
    kw_z = kw.copy()
    kw_z[el[:120]] = rng.uniform(0.01, 0.3, 120)
    ey, ez, ex = len(g.ys) - 1, len(g.zs) - 1, len(g.xs) - 1
    top = np.arange(n).reshape(ey, ez, ex)[:, -1, :].ravel()     # a whole row of mixed elements
    kw[top], kw_z[top] = 0.6, 0.05
    el = np.union1d(el, top)
    sk_kw, sk_z = np.empty(n), np.empty(n)
    sk_kw[eorder], sk_z[eorder] = kw, kw_z
    rep = lambda w: np.repeat(w[:, None], nqp, axis=1)          # noqa: E731
    k_ref = (conduction.assemble(basis, kw=rep(sk_kw)) - conduction_z.assemble(basis, kw=rep(sk_kw))
             + conduction_z.assemble(basis, kw=rep(sk_z)))[perm][:, perm]
    kz_ref = conduction_z.assemble(basis, kw=rep(sk_z))[perm][:, perm]
    u = rng.standard_normal(g.n_nodes)
    fresh = TensorOperator(g, kw, None, vertical=True, kw_z=kw_z)
    reweighted = TensorOperator(g, vertical=True)
    reweighted.reweight(el[::2], kw[el[::2]], 1.0, kw_z[el[::2]])
    reweighted.reweight(el[1::2], kw[el[1::2]], 1.0, kw_z[el[1::2]])
    for op in (fresh, reweighted):
        assert close(op(u.reshape(g.solver_shape)).ravel(), k_ref @ u)
        assert close(op.vertical(u.reshape(g.solver_shape)).ravel(), kz_ref @ u)
    reweighted.reweight(el, kw[el], 1.0)          # isotropic again
    assert close(reweighted(u), TensorOperator(g, kw, None, vertical=True)(u))


def test_stability_bound_is_tight_upper_bound(setup):
    g, mesh, perm, _, _ = setup
    n_el = (len(g.ys) - 1) * (len(g.zs) - 1) * (len(g.xs) - 1)
    for kw, slack in ((None, 1.05), (np.random.default_rng(5).uniform(0.1, 1.0, n_el), 2.0)):
        op = TensorOperator(g, kw)
        d = sp.diags(1.0 / np.sqrt(np.ravel(op.lumped_mass)))
        lam = sp.linalg.eigsh(d @ op.assembled() @ d, k=1, which="LA", return_eigenvectors=False)[0]
        assert lam <= op.stability_eigenvalue() < slack * lam
    # box element eigenvalue 4 / h_min² (the tensor path's closed form) = the CSR path's eigvalsh
    h = np.array([30e-6, 20e-6, 45e-6])
    ke = box_stiffness(*h[:, None])[0]
    assert np.linalg.eigvalsh(ke / np.prod(h) * 8).max() == pytest.approx(4 / h.min() ** 2, rel=1e-12)


def test_csr_operator_on_a_tetrahedral_mesh():
    mesh = MeshTet.init_tensor(np.linspace(0, 1e-3, 6), np.linspace(0, 1e-3, 5), np.linspace(-5e-4, 0, 4))
    rng = np.random.default_rng(6)
    op = CsrOperator(mesh, rng.uniform(0.1, 1.0, mesh.t.shape[1]))
    assert np.abs(op.matrix.sum(axis=1)).max() < 1e-12 * abs(op.matrix).max()   # conserves energy
    assert op.lumped_mass.sum() == pytest.approx(0.5e-9, rel=1e-12)
    assert op.stability_eigenvalue() > 0


def test_laser_and_facet_forms_equal_the_closed_forms(setup):
    g, mesh, perm, _, _ = setup
    top = mesh.facets_satisfying(lambda x: np.isclose(x[2], 0.0))
    fb = FacetBasis(mesh, ElementHex1(), facets=top, intorder=12)
    nodes = np.unravel_index(np.arange(g.n_nodes), g.solver_shape)
    on_top = nodes[1] == len(g.zs) - 1
    areas = facet_area.assemble(fb)[perm][on_top].reshape(len(g.ys), len(g.xs))
    assert close(areas, g.top_areas(), 1e-13)
    xl, yl, r = 3e-6, -7e-6, 50e-6
    f = laser.assemble(fb, xl=xl, yl=yl, r=r)[perm][on_top].reshape(len(g.ys), len(g.xs))
    exact = surface_load(g.xs, g.ys, np.array([[xl, yl]]), 1.0, 1.0, r).T
    assert f.sum() == pytest.approx(1.0, rel=1e-6) and close(f, exact, 1e-6)


@pytest.mark.parametrize("physics", [{}, dict(powder_layer_m=40e-6, evaporation=True, liquid_k_factor_xy=2.0,
                                              liquid_k_factor_z=1.5)])
def test_thermal_model_same_with_either_operator(physics):
    from fe_node.scan import ScanPlan
    from fe_node.settings import Settings
    from fe_node.solver import ThermalModel

    coarse = dict(h_fine_m=40e-6, margin_m=0.4e-3, depth_m=0.5e-3, fine_pad_m=120e-6, fine_depth_m=120e-6,
                  h_max_m=0.2e-3)
    plan = ScanPlan.layer(2, 0.4e-3, 0.1e-3)
    models = [ThermalModel(Settings(**coarse, **physics, operator=op), plan) for op in ("tensor", "csr")]
    for _ in range(12):
        obs = [m.step(250.0, 0.8) for m in models]
    assert obs[0].area_m2 > 0 and models[0].n_substeps == models[1].n_substeps
    assert obs[1].area_m2 == pytest.approx(obs[0].area_m2, rel=1e-12)
    assert close(models[1].temperature(), models[0].temperature(), 1e-11)
    if physics:
        assert models[0].powder.consolidated.sum() > 0


@pytest.mark.parametrize("box", [(slice(2, 6), slice(3, 7), slice(4, 9)),      # inside
                                 (slice(0, 3), slice(0, 2), slice(0, 4)),      # at the low faces
                                 (slice(-3, None), slice(-2, None), slice(-4, None))])   # at the high faces
def test_add_vertical_on_a_box_equals_the_full_product(setup, box):
    """K_z of a field zero outside a node box, from the box alone (both operators) = the full K_z of
    the CSR operator (assembled from the form)."""
    g, mesh, perm, eorder, _ = setup
    rng = np.random.default_rng(7)
    box = tuple(slice(*s.indices(n)[:2]) for s, n in zip(box, g.solver_shape))
    n = eorder.size
    shape = (len(g.ys) - 1, len(g.zs) - 1, len(g.xs) - 1)
    kw = np.broadcast_to(rng.uniform(0.1, 1.0, shape[1])[None, :, None], shape).ravel().copy()
    el = rng.choice(n, 60, replace=False)
    u = np.zeros(g.solver_shape)
    u[box] = rng.standard_normal(u[box].shape)
    ops = (TensorOperator(g, kw, vertical=True), CsrOperator(mesh, kw[np.argsort(eorder)], order=perm, vertical=True))
    for part in (el[:50], el[50:]):      # the tensor correction: 50 in its main block, 10 in its recent one
        weights = rng.uniform(0.1, 2.0, part.size)
        for op in ops:
            op.reweight(part if isinstance(op, TensorOperator) else eorder[part], weights, 1.0)
    reference = ops[1].vertical(u)
    for op in ops:
        out = rng.standard_normal(g.solver_shape)
        expected = out + reference
        op.add_vertical(u[box].copy(), box, out)
        assert close(out, expected, 1e-12)


def test_refactoring_keeps_the_operator_and_bounds_the_correction(setup):
    """Tracks consolidating along x: the factors are rebuilt from the rows' medians as the correction
    grows, and the operator stays the fresh one of the same weights."""
    g, mesh, perm, eorder, _ = setup
    rng = np.random.default_rng(8)
    ey, ez, ex = shape = (len(g.ys) - 1, len(g.zs) - 1, len(g.xs) - 1)
    kw = np.broadcast_to(np.where(np.arange(ez) >= ez - 2, 0.05, 1.0)[None, :, None], shape).copy()
    op = TensorOperator(g, kw.ravel(), vertical=True)
    u = rng.standard_normal(g.n_nodes)
    box = (slice(3, 8), slice(ez - 3, ez + 1), slice(2, 12))
    u_box = rng.standard_normal((5, 4, 10))
    op.add_vertical(u_box, box, np.zeros(g.solver_shape))        # the box's (y, z) block, before
    sizes, refactored = [], 0
    for j in range(2, ey - 2):                   # one track per y row of elements, in chunks along x
        for i0 in range(0, ex, 5):
            row = np.ravel_multi_index(np.meshgrid([j], [ez - 2, ez - 1], np.arange(i0, min(i0 + 5, ex)),
                                                   indexing="ij"), shape).ravel()
            before = op._corr.n_elements
            op.reweight(row, 1.0, 1.0)
            kw.ravel()[row] = 1.0
            refactored += op._corr.n_elements < before
            sizes.append(op._corr.n_elements)
    fresh = TensorOperator(g, kw.ravel(), vertical=True)
    assert close(op(u), fresh(u)) and close(op.vertical(u), fresh.vertical(u))
    on_box, out = np.zeros(g.solver_shape), np.zeros(g.solver_shape)
    on_box[box] = u_box
    op.add_vertical(u_box, box, out)
    assert close(out, fresh.vertical(on_box))
    assert abs(op.assembled() - fresh.assembled()).max() <= 1e-12 * abs(fresh.assembled()).max()
    assert refactored >= 2 and max(sizes) <= 2 * 2 * ex      # two rows of two layers, not the 2 (ey - 4) rows


@pytest.fixture(scope="module")
def corner_basis(setup):
    """The forms integrated at the 8 corners of each element (nodal quadrature; the hex reference is the unit cube)."""
    _, mesh, *_ = setup
    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)]).T
    return Basis(mesh, ElementHex1(), quadrature=(corners, np.full(8, 1.0 / 8.0)))


def test_nodal_operator_equals_the_forms_at_the_corners(setup, corner_basis):
    """``nodal=True`` (the coarser levels of the multi-level mesh) is ``conduction`` with nodal
    quadrature, fresh or re-weighted, with vertical weights; its element bound holds."""
    g, mesh, perm, eorder, _ = setup
    rng = np.random.default_rng(11)
    n = eorder.size
    kw, kw_z = rng.uniform(0.2, 1.0, n), np.ones(n)
    el = rng.choice(n, 150, replace=False)
    kw_z[el] = rng.uniform(0.01, 0.3, el.size)
    kw_z[kw_z == 1.0] = kw[kw_z == 1.0]
    sk_kw, sk_z = np.empty(n), np.empty(n)
    sk_kw[eorder], sk_z[eorder] = kw, kw_z
    rep = lambda w: np.repeat(w[:, None], 8, axis=1)          # noqa: E731
    b = corner_basis
    k_ref = (conduction.assemble(b, kw=rep(sk_kw)) - conduction_z.assemble(b, kw=rep(sk_kw))
             + conduction_z.assemble(b, kw=rep(sk_z)))[perm][:, perm]
    u = rng.standard_normal(g.n_nodes)
    fresh = TensorOperator(g, kw, None, kw_z=kw_z, nodal=True)
    reweighted = TensorOperator(g, nodal=True)
    reweighted.reweight(np.arange(n), kw, 1.0, kw_z)
    for op in (fresh, reweighted):
        assert close(op(u.reshape(g.solver_shape)).ravel(), k_ref @ u)
    assert abs(fresh.assembled() - k_ref).max() <= 1e-12 * abs(k_ref).max()
    d = sp.diags(1.0 / np.sqrt(np.ravel(fresh.lumped_mass)))
    lam = sp.linalg.eigsh(d @ fresh.assembled() @ d, k=1, which="LA", return_eigenvectors=False)[0]
    assert lam <= fresh.stability_eigenvalue()


def test_nodal_operator_is_an_m_matrix_where_the_exact_one_is_not():
    """Flat elements (200 x 200 x 50 µm, the part level's top rows) with an insulating powder row's
    vertical weight: the exact trilinear stiffness couples in-plane neighbours positively (a hot
    node cools them), the nodal one has no positive off-diagonal entry."""
    zs = np.array([-0.4e-3, -0.2e-3, -0.1e-3, -0.05e-3, 0.0])
    g = Grid(np.linspace(0.0, 2e-3, 11), np.linspace(0.0, 2e-3, 11), zs)
    ny, nz, nx = g.solver_shape
    kw_z = np.ones((ny - 1, nz - 1, nx - 1))
    kw_z[:, -1, :] = 0.05
    for nodal, positive in ((False, True), (True, False)):
        k = TensorOperator(g, None, None, kw_z=kw_z.ravel(), nodal=nodal).assembled().tocoo()
        off = k.data[k.row != k.col]
        assert (off.max() > 1e-12 * abs(k.data).max()) == positive


def test_a_moved_operator_equals_a_fresh_one(setup):
    """``moved`` on a translate of the grid (a fine box that moved by whole cells) with other
    weights equals the operator built there afresh; a grid of other spacings is refused."""
    g, *_ = setup
    rng = np.random.default_rng(21)
    shape = (len(g.ys) - 1, len(g.zs) - 1, len(g.xs) - 1)
    kw = np.broadcast_to(rng.uniform(0.05, 1.0, shape[1])[None, :, None], shape).copy()
    kw[:, :, : shape[2] // 3] = 1.0                     # consolidated behind, powder ahead
    op = TensorOperator(g, kw.ravel(), None, vertical=True)
    moved_grid = Grid(g.xs + 7 * 30e-6, g.ys - 2 * 30e-6, g.zs)
    kw2 = np.roll(kw, -2, axis=2)
    kw2.ravel()[rng.choice(kw2.size, 30, replace=False)] = 0.5
    moved = op.moved(moved_grid, kw2.ravel())
    fresh = TensorOperator(moved_grid, kw2.ravel(), None, vertical=True)
    u = rng.standard_normal(g.solver_shape)
    assert close(moved(u), fresh(u)) and close(moved.vertical(u), fresh.vertical(u))
    assert moved.stability_eigenvalue() == pytest.approx(fresh.stability_eigenvalue(), rel=1e-9)
    assert close(op(u), TensorOperator(g, kw.ravel(), None, vertical=True)(u))     # the old one is untouched
    assert op.moved(Grid(g.xs * 1.1, g.ys, g.zs), kw2.ravel()) is None
