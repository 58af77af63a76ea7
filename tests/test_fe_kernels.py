"""The compiled loops of ``fe_node.kernels`` equal the numpy forms they replace, bit for bit."""
import numpy as np
import pytest
import scipy.sparse as sp

from fe_node.kernels import piecewise_linear, tensor_apply, warm
from fe_node.material import Constitutive, Material


def test_tensor_apply_equals_the_sparse_product_and_the_x_passes():
    """Two CSR factors with different patterns (one of them with an empty row) times U, then the
    tridiagonal x factors: scipy's product and the numpy passes, bit for bit."""
    rng = np.random.default_rng(4)
    p, nx = 37, 53
    a = sp.random(p, p, density=0.15, format="csr", random_state=1)
    b = sp.random(p, p, density=0.2, format="csr", random_state=2)
    a.data[a.indptr[3]:a.indptr[4]] = 0.0
    a.eliminate_zeros()
    u = rng.standard_normal((p, nx))
    kd, ko, md, mo = (rng.standard_normal(n) for n in (nx, nx - 1, nx, nx - 1))
    v, w = a @ u, b @ u
    ref = v * kd + w * md
    ref[:, 1:] += v[:, :-1] * ko + w[:, :-1] * mo
    ref[:, :-1] += v[:, 1:] * ko + w[:, 1:] * mo
    out = np.empty((p, nx))
    tensor_apply(a.indptr, a.indices, a.data, b.indptr, b.indices, b.data, u, kd, ko, md, mo, out)
    np.testing.assert_array_equal(out, ref)


def test_kirchhoff_is_the_table_clipped_at_its_ends():
    """On the table's nodes phi is np.interp of its nodes; inside an interval it is the interval's
    line (the numpy form, bitwise); below the table the first line, above it the liquid line."""
    law = Constitutive(Material.in625())
    h = np.linspace(law._h0 - 1e8, law._h0 + (law._imax + 3) / law._inv_dh, 20_011)
    i = np.clip(((h - law._h0) * law._inv_dh).astype(np.intp), 0, law._imax)
    np.testing.assert_array_equal(law.kirchhoff(h), law._p_b[i] * h + law._p_a[i])
    out = np.empty((7, 3))
    grid = h[5_000:5_021].reshape(7, 3)
    assert law.kirchhoff(grid, out=out) is out
    np.testing.assert_array_equal(out, law.kirchhoff(grid.ravel()).reshape(7, 3))
    with pytest.raises(ValueError, match="C-contiguous"):
        law.kirchhoff(grid, out=np.empty((3, 7)).T)          # a view whose reshape would be a copy
    a, b, out1 = np.array([1.0, 2.0]), np.array([10.0, 20.0]), np.empty(4)
    piecewise_linear(np.array([-5.0, 0.5, 1.5, 9.0]), 0.0, 1.0, 1, a, b, out1)
    np.testing.assert_array_equal(out1, [-49.0, 6.0, 32.0, 182.0])


def test_temperature_is_the_table_clipped_at_its_ends():
    """T(H) through the compiled table equals the numpy form bit for bit, on any shape and stride,
    and is a scalar for a scalar."""
    law = Constitutive(Material.in625())
    h = np.linspace(law._h0 - 1e8, law._h0 + (law._imax + 3) / law._inv_dh, 20_013).reshape(3, 6671)
    i = np.clip(((h - law._h0) * law._inv_dh).astype(np.intp), 0, law._imax)
    np.testing.assert_array_equal(law.temperature(h), law._t_a[i] + law._t_b[i] * h)
    np.testing.assert_array_equal(law.temperature(h[:, ::7].T), (law._t_a[i] + law._t_b[i] * h)[:, ::7].T)
    scalar = law.temperature(h[1, 17])
    assert np.ndim(scalar) == 0 and scalar == law._t_a[i[1, 17]] + law._t_b[i[1, 17]] * h[1, 17]


def test_consolidation_marks_the_elements_whose_corner_mean_passes_the_liquidus():
    """The compiled consolidation equals the numpy form: the mean of the eight corners, summed in
    their order, against the liquidus; already consolidated elements are not returned again."""
    from fe_node.powder import PowderBed

    rng = np.random.default_rng(7)
    t = rng.uniform(1500.0, 1760.0, (6, 4, 9))
    bed = PowderBed.__new__(PowderBed)
    bed.k0, bed.t_liquidus = 5, 1623.0
    bed.consolidated = rng.uniform(size=(5, 3, 8)) < 0.2
    before = bed.consolidated.copy()
    mean = 0.125 * (t[:-1, :-1, :-1] + t[:-1, :-1, 1:] + t[:-1, 1:, :-1] + t[:-1, 1:, 1:]
                    + t[1:, :-1, :-1] + t[1:, :-1, 1:] + t[1:, 1:, :-1] + t[1:, 1:, 1:])
    new = (mean > 1623.0) & ~before
    j, k, i = np.nonzero(new)
    melted = bed.consolidate(t)
    np.testing.assert_array_equal(melted, np.ravel_multi_index((j, k + 5, i), (5, 8, 8)))
    np.testing.assert_array_equal(bed.consolidated, before | new)
    assert new.any() and (before & (mean > 1623.0)).any() and len(bed.consolidate(t)) == 0


def test_warm_compiles_every_kernel_with_the_plants_types():
    """After ``warm`` (what a plant runs when it is built) no kernel compiles again in a step."""
    import fe_node.kernels as kernels
    from fe_node.scenarios import scenario
    from fe_node.solver import ThermalModel

    warm()
    compiled = {name: len(getattr(kernels, name).signatures) for name in
                ("tensor_apply", "piecewise_linear", "element_apply", "csr_box_rows", "element_apply_box",
                 "evaporate_nodes", "drill_columns", "melt_powder", "area_and_extent", "deepest_line")}
    sc = scenario("double-track", h_fine_m=50e-6, track_length_m=1e-3)
    model = ThermalModel(sc.settings, sc.plan)
    for _ in range(30):
        model.step(*sc.profile.command(model.step_index))
    assert {name: len(getattr(kernels, name).signatures) for name in compiled} == compiled
