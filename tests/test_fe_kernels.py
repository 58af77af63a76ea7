"""The compiled loops of ``fe_node.kernels`` equal the numpy forms they replace, bit for bit."""
import numpy as np
import pytest
import scipy.sparse as sp

from fe_node.kernels import forward_euler, piecewise_linear, tensor_apply, vertical_box, warm
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
    compiled = {name: len(f.signatures) for name, f in vars(kernels).items()
                if hasattr(f, "signatures") and not name.startswith("_")}
    assert len(compiled) >= 14 and all(compiled.values())
    sc = scenario("double-track", h_fine_m=50e-6, track_length_m=1e-3)
    model = ThermalModel(sc.settings, sc.plan)
    for _ in range(30):
        model.step(*sc.profile.command(model.step_index))
    assert {name: len(getattr(kernels, name).signatures) for name in compiled} == compiled


def test_the_fused_sub_step_passes_equal_their_numpy_forms():
    """The explicit sub-step's compiled passes equal the numpy forms they replace, bit for bit: the
    Kirchhoff variable with the box of nodes above a floor (none above: False), the mushy integral
    added on that box, the vertical term's x passes, and the forward-Euler update with the top row."""
    rng = np.random.default_rng(11)
    law = Constitutive(Material.in625())
    floor = law.mushy_floor
    h = rng.uniform(0.2, 0.9, (9, 7, 13)) * floor
    h[2:5, 4:7, 3:11] = rng.uniform(0.95, 1.6, (3, 3, 8)) * floor
    phi, box = np.empty(h.shape), np.zeros(6, dtype=np.intp)
    assert law.kirchhoff_above(h, floor, phi, box)
    np.testing.assert_array_equal(phi, law.kirchhoff(h))
    j, k, i = np.nonzero(h > floor)
    np.testing.assert_array_equal(box, [j.min(), j.max() + 1, k.min(), k.max() + 1, i.min(), i.max() + 1])
    assert not law.kirchhoff_above(h, 2 * floor, phi, box)
    sl = tuple(slice(box[2 * d], box[2 * d + 1]) for d in range(3))
    psi = law.mushy_integral(h[sl])
    assert np.count_nonzero(psi) and np.count_nonzero(psi == 0)        # liquid, mushy and solid nodes
    ref = phi.copy()
    ref[sl] += 0.3 * psi
    u_box = law.add_mushy_integral(h, box, 0.3, 1.7, phi)
    np.testing.assert_array_equal(phi, ref)
    np.testing.assert_array_equal(u_box, 1.7 * psi)

    cz = sp.random(9 * 7, 9 * 7, density=0.2, format="csr", random_state=3)
    md, mo = rng.standard_normal(13), rng.standard_normal(12)
    rows = np.array([1, 6, 3, 7, 2, 12])                 # the box and its neighbours
    w = (cz @ np.pad(u_box, [(box[2 * d], h.shape[d] - box[2 * d + 1]) for d in range(3)]).reshape(63, 13))
    w = w.reshape(9, 7, 13)[1:6, 3:7, 2:12].reshape(20, 10)
    res = w * md[2:12]
    res[:, 1:] += w[:, :-1] * mo[2:11]
    res[:, :-1] += w[:, 1:] * mo[2:11]
    out = rng.standard_normal(h.shape)
    expected = out.copy()
    expected[1:6, 3:7, 2:12] += res.reshape(5, 4, 10)
    vertical_box(cz.indptr, cz.indices, cz.data, 7, rows, box[0], box[2], box[4], u_box, md, mo, out)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)      # the CSR rows sum in scipy's order

    kphi, c = rng.standard_normal(h.shape), rng.uniform(size=h.shape)
    top, c_top = rng.standard_normal((9, 13)), rng.uniform(size=(9, 13))
    ref = h.copy()
    ref -= kphi * c
    ref[:, -1, :] += top * c_top
    forward_euler(h, kphi, c, top, c_top)
    np.testing.assert_array_equal(h, ref)



def test_the_compiled_passes_refuse_arrays_they_would_overrun():
    """The compiled passes do not check their indices: their callers refuse mismatched arrays first."""
    from fe_node.boundary import evaporate_top

    law, h = Constitutive(Material.in625()), np.ones((3, 2, 4))
    with pytest.raises(ValueError, match="kirchhoff_above"):
        law.kirchhoff_above(h, 0.5, np.empty((3, 2, 3)), np.zeros(6, dtype=np.intp))
    with pytest.raises(ValueError, match="kirchhoff_above"):
        law.kirchhoff_above(h, 0.5, np.empty((3, 2, 4)), np.zeros(5, dtype=np.intp))
    with pytest.raises(ValueError, match="evaporate_top"):
        evaporate_top(h, np.ones((3, 2, 4)), law, np.ones((3, 4)), np.empty(11))
    with pytest.raises(ValueError, match="evaporate_top"):
        evaporate_top(h, np.ones((3, 2, 4)), law, np.ones((4, 3)), np.empty(12))
