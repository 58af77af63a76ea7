"""Correctness tests of the FE plant core (fe_node): operators, source, energy, geometry."""
import numpy as np
import pytest

from fe_node.material import Constitutive, Material
from fe_node.mesh import Grid, graded_axis
from fe_node.observe import area_above, pool_geometry
from fe_node.scan import ScanPlan
from fe_node.settings import Settings
from fe_node.solver import ThermalModel
from fe_node.source import hat_gaussian_integrals, surface_load

COARSE = dict(h_fine_m=40e-6, margin_m=0.5e-3, depth_m=0.6e-3, fine_pad_m=120e-6,
              fine_depth_m=120e-6, h_max_m=0.2e-3)


def small_grid():
    ax = dict(h=30e-6, growth=1.4, h_max=0.2e-3)
    return Grid(graded_axis(-0.4e-3, 0.5e-3, -0.1e-3, 0.2e-3, **ax),
                graded_axis(-0.3e-3, 0.3e-3, -0.1e-3, 0.1e-3, **ax),
                graded_axis(-0.4e-3, 0.0, -0.1e-3, 0.0, **ax))


def test_graded_axis_bounds_and_fine_size():
    x = graded_axis(-1e-3, 2e-3, 0.0, 1e-3, 25e-6, 1.35, 0.3e-3)
    assert x[0] == -1e-3 and x[-1] == 2e-3 and np.all(np.diff(x) > 0)
    fine = np.diff(x[(x >= 0) & (x <= 1e-3)])
    assert np.allclose(fine, 25e-6) and np.diff(x).max() <= 0.3e-3 + 1e-12


def test_constitutive_tables_roundtrip():
    law = Constitutive(Material.in625())
    t = np.array([300.0, 900.0, 1500.0, 1700.0, 4000.0])
    assert np.allclose(law.temperature(law.enthalpy(t)), t, atol=1e-3)
    # latent heat is released between solidus and liquidus
    m = law.material
    dh = law.enthalpy(m.t_liquidus) - law.enthalpy(m.t_solidus)
    sensible = m.rho * 0.5 * (m.cp(m.t_solidus) + m.cp(m.t_liquidus)) * 60.0
    assert dh == pytest.approx(m.rho * m.latent + sensible, rel=1e-6)
    c = Constitutive(Material.constant(20.0, 8000.0, 500.0))
    assert np.allclose(c.kirchhoff(c.enthalpy(t)), t) and c.max_diffusivity == pytest.approx(5e-6)


def test_hat_gaussian_integrals_exact():
    x = np.sort(np.random.default_rng(1).uniform(-3e-4, 3e-4, 40))
    x[0], x[-1] = -4e-4, 4e-4
    g = hat_gaussian_integrals(x, 1.3e-5, 2e-5)
    assert g.sum() == pytest.approx(2e-5 * np.sqrt(2 * np.pi), rel=1e-12)
    # brute force against fine quadrature of the hat functions
    xf = np.linspace(-4e-4, 4e-4, 400001)
    gauss = np.exp(-((xf - 1.3e-5) ** 2) / (2 * 4e-10))
    for i in (5, 17, 20, 30):
        hat = np.interp(xf, x, np.eye(len(x))[i])
        assert g[i] == pytest.approx(np.trapezoid(hat * gauss, xf), rel=1e-6, abs=1e-15)


def test_surface_load_deposits_a_p():
    g = small_grid()
    pos = np.array([[1e-5 * k, 3e-6] for k in range(8)])
    load = surface_load(g.xs, g.ys, pos, 237.0, 0.4, 50e-6)
    assert load.sum() == pytest.approx(0.4 * 237.0, rel=1e-13) and load.min() >= 0


def test_surface_load_on_its_window_equals_the_whole_surface_integral(monkeypatch):
    """The load is integrated on the nodes within ``LOAD_REACH_SIGMAS`` of the beam only: equal, to the
    rounding of the load, to integrating every node of the surface (beams inside and at the edge)."""
    from fe_node import source

    xs, ys = np.linspace(-1e-3, 1e-3, 81), np.concatenate([np.linspace(-4e-4, 0, 5), np.linspace(2.5e-5, 2e-4, 8)])
    beams = [np.array([[1e-5 * k, 3e-6] for k in range(6)]), np.array([[-1e-3, 2e-4], [-0.99e-3, 1.9e-4]])]
    windowed = [surface_load(xs, ys, pos, 237.0, 0.4, 50e-6) for pos in beams]
    monkeypatch.setattr(source, "LOAD_REACH_SIGMAS", np.inf)
    for pos, load in zip(beams, windowed, strict=True):
        whole = surface_load(xs, ys, pos, 237.0, 0.4, 50e-6)
        assert np.abs(load - whole).max() <= 1e-14 * whole.max()


def test_surface_load_of_an_oblique_path_is_the_mean_of_its_positions_loads():
    """Positions at different y (a hatch rotated by 67°) take the one-matrix path: the mean of each
    position's own load (each beam inside the surface, so each deposits a P)."""
    xs, ys = np.linspace(-5e-4, 5e-4, 41), np.linspace(-4e-4, 4e-4, 33)
    step = 2.5e-6 * np.array([np.cos(np.radians(67.0)), np.sin(np.radians(67.0))])
    pos = np.array([1e-5, -2e-5]) + np.arange(6)[:, None] * step
    each = np.mean([surface_load(xs, ys, p[None, :], 237.0, 0.4, 50e-6) for p in pos], axis=0)
    load = surface_load(xs, ys, pos, 237.0, 0.4, 50e-6)
    assert np.abs(load - each).max() <= 1e-13 * each.max()


@pytest.fixture(scope="module")
def coarse_track():
    s = Settings(**COARSE)
    model = ThermalModel(s, ScanPlan.single(1.2e-3))
    obs = [model.initial_observation()]
    while not model.done:
        obs.append(model.step(250.0, 0.8))
    return model, obs


def test_absorbed_energy_and_conservation(coarse_track):
    model, obs = coarse_track
    n = len(obs) - 1
    assert n == 30 and obs[-1].time_s == pytest.approx(30 * 50e-6)
    assert obs[-1].energy_absorbed_j == pytest.approx(0.4 * 250.0 * 50e-6 * n, rel=1e-12)
    assert obs[-1].energy_lost_j > 0
    assert max(abs(o.energy_error_pct) for o in obs[1:]) < 1e-6
    assert obs[0].step == 0 and obs[0].area_m2 == 0.0 and obs[0].t_ahead_k == pytest.approx(300.0, abs=1e-5)


def test_centred_track_is_symmetric(coarse_track):
    model, obs = coarse_track
    t = model.temperature()
    ys = model.grid.ys
    assert np.allclose(ys, -ys[::-1], atol=1e-15)
    assert np.allclose(t, t[:, ::-1, :], rtol=1e-9)
    assert obs[-1].y_m == 0.0 and obs[-1].direction == (1.0, 0.0)


def test_melt_pool_is_plausible(coarse_track):
    _, obs = coarse_track
    o = obs[-1]
    assert 0.03e-6 < o.area_m2 < 0.12e-6 and 80e-6 < o.width_m < 200e-6
    assert 30e-6 < o.depth_m < 100e-6 and o.length_m > o.width_m
    assert 0 < o.cross_section_m2 < o.width_m * o.depth_m
    assert o.t_peak_k > 1623.0


def test_t_ahead_location(coarse_track):
    model, obs = coarse_track
    o = obs[-1]   # rule of paper footnote 1, checked against the public image sampler
    x_ahead = o.x_m + (o.speed_m_s * 50e-6 + 50e-6) * o.direction[0]
    img, ext = model.temperature_image(half_length_m=0.2e-3, half_width_m=0.05e-3, pixel_m=10e-6)
    px = np.linspace(ext[0], ext[1], img.shape[1])
    py = np.linspace(ext[2], ext[3], img.shape[0])
    col = np.argmin(abs(px - x_ahead))
    assert px[col] == pytest.approx(x_ahead, abs=1e-9)
    assert img[np.argmin(abs(py - o.y_m)), col] == pytest.approx(o.t_ahead_k, rel=1e-9)
    assert o.t_ahead_k < 1000.0   # ahead of the pool, barely heated


def test_area_extraction_on_elliptical_field():
    a, b = 300e-6, 70e-6
    # fine nodes (5 µm) so that the bilinear interpolation error of the field is
    # ~1e-4: what remains is the extraction error
    xs = graded_axis(-0.5e-3, 0.5e-3, -0.4e-3, 0.4e-3, 5e-6, 1.3, 0.1e-3)
    ys = graded_axis(-0.2e-3, 0.2e-3, -0.1e-3, 0.1e-3, 5e-6, 1.3, 0.1e-3)
    zs = np.linspace(-0.2e-3, 0.0, 41)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    # a field that is linear along every grid line through the level set is not
    # available for an ellipse; use T = exp(-r²) so the bilinear error is O(h²)
    r2 = (X / a) ** 2 + (Y / b) ** 2 + (Z / 50e-6) ** 2
    t = 2000.0 * np.exp(1.0 - r2)            # level 2000 <=> ellipsoid r2 = 1
    geo = pool_geometry(t, xs, ys, zs, 2000.0)
    assert geo["area_m2"] == pytest.approx(np.pi * a * b, rel=1e-3)
    assert geo["length_m"] == pytest.approx(2 * a, rel=1e-3)
    assert geo["width_m"] == pytest.approx(2 * b, rel=1e-3)
    assert geo["depth_m"] == pytest.approx(50e-6, rel=1e-3)
    assert geo["cross_section_m2"] == pytest.approx(np.pi * b * 50e-6 / 2, rel=1e-3)


def test_area_exact_for_piecewise_linear_field():
    # 1 - |x| - |y|/2 is linear per cell on a grid with a node at 0; {f > 1/2} is a
    # diamond with half-diagonals 1/2 and 1, area 1, recovered to round-off
    xs = np.linspace(-1, 1, 11)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    f = 1 - np.abs(X) - np.abs(Y) * 0.5
    assert area_above(f, xs, xs, 0.5, n_refine=4) == pytest.approx(1.0, rel=1e-12)


def test_lowest_crossing_is_the_lowest_segment_start():
    """The reference depth's shortcut gives :func:`segments_above`'s lowest ``lo`` and its first row, ties
    included (the numpy form the compiled depth is compared with below)."""
    from tests.pool_reference import lowest_crossing, segments_above

    rng = np.random.default_rng(3)
    zs = np.cumsum(rng.uniform(5e-6, 20e-6, 9))
    for level, shift, cold in ((0.7, 0.0, 0), (0.7, 0.5, 2), (0.2, 0.0, 3)):
        values = rng.uniform(0, 1, (400, 9)) ** 3 + shift * np.linspace(0, 1, 9)
        values[:, :cold] *= 0.1                      # no row above at its lowest nodes
        values[:5] = 0.0                             # rows with nothing above come first
        _, lo, _ = segments_above(values, zs, level)
        values[300] = values[int(np.nanargmin(lo))]   # a later row ties with the lowest
        _, lo, _ = segments_above(values, zs, level)
        assert lowest_crossing(values, zs, level) == (int(np.nanargmin(lo)), float(np.nanmin(lo)))


def _pool_fields():
    """Fields for the geometry comparison: random lumps on a graded block, one with its deepest lines
    tied (mirror-symmetric in y), one liquid down to the block's bottom, and a state of the FE plant."""
    rng = np.random.default_rng(11)
    xs = np.cumsum(rng.uniform(10e-6, 30e-6, 33)) - 4e-4
    ys = np.cumsum(rng.uniform(10e-6, 30e-6, 12)) - 1.5e-4
    zs = np.cumsum(rng.uniform(8e-6, 25e-6, 14)) - 2.5e-4
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    for _ in range(4):
        c = rng.uniform(-1e-4, 1e-4, 3)
        r2 = ((X - c[0]) / 2e-4) ** 2 + ((Y - 0.3 * c[1]) / 7e-5) ** 2 + ((Z - zs[-1]) / 8e-5) ** 2
        yield 2000.0 * np.exp(1.0 - r2) + rng.normal(0, 5.0, X.shape), xs, ys, zs
    half = np.cumsum(rng.uniform(10e-6, 30e-6, 6))
    sym = np.concatenate([-half[::-1], [0.0], half])
    Xs, Ys, Zs = np.meshgrid(xs, sym, zs, indexing="ij")
    yield 2000.0 * np.exp(1.0 - (Xs / 2e-4) ** 2 - (Ys / 7e-5) ** 2 - ((Zs - zs[-1]) / 8e-5) ** 2), xs, sym, zs
    yield 2000.0 * np.exp(1.0 - (X / 2e-4) ** 2 - (Y / 7e-5) ** 2 - ((Z - zs[-1]) / 5e-4) ** 2), xs, ys, zs
    model = ThermalModel(Settings(**COARSE), ScanPlan.single(1.2e-3))
    for _ in range(25):
        model.step(250.0, 0.8)
    g = model.grid
    yield g.to_xyz(model.law.temperature(model._h)), g.xs, g.ys, g.zs


def test_compiled_pool_geometry_equals_the_numpy_form():
    """Area, length, width, depth and cross-section of the compiled geometry equal the numpy form to
    rounding, on fields with ties and liquid down to the bottom and on an FE state."""
    from tests.pool_reference import pool_geometry as reference

    level = 1623.0
    for t3, xs, ys, zs in _pool_fields():
        got, ref = pool_geometry(t3, xs, ys, zs, level), reference(t3, xs, ys, zs, level)
        assert ref["area_m2"] > 0 and ref["depth_m"] > 0
        for key, value in ref.items():
            assert got[key] == pytest.approx(value, rel=1e-12, abs=1e-20), key


def test_step_rejects_bad_commands():
    model = ThermalModel(Settings(**COARSE), ScanPlan.single(0.2e-3))
    for p, v in [(-1.0, 0.8), (100.0, 0.0), (float("nan"), 0.8), (100.0, -1.0)]:
        with pytest.raises(ValueError):
            model.step(p, v)
    while not model.done:
        model.step(0.0, 0.8)
    with pytest.raises(RuntimeError):
        model.step(100.0, 0.8)


def test_track_change_and_variable_speed_keep_energy_exact():
    plan = ScanPlan.layer(2, 0.3e-3, 0.1e-3)
    model = ThermalModel(Settings(**COARSE), plan)
    obs, speeds = [], [0.8, 1.0, 0.6, 0.9]
    while not model.done:
        obs.append(model.step(200.0, speeds[model.step_index % 4]))
    tracks = [o.track for o in obs]
    assert tracks[0] == 0 and tracks[-1] == 1 and sorted(tracks) == tracks
    second = [o for o in obs if o.track == 1]
    assert all(o.direction == (-1.0, 0.0) and o.y_m == pytest.approx(0.05e-3) for o in second)
    travelled = sum(o.speed_m_s for o in obs[:-1]) * 50e-6
    assert travelled < plan.total_length <= travelled + obs[-1].speed_m_s * 50e-6
    # the last step is only partly on the plan: the laser is off past its end
    frac = (plan.total_length - travelled) / (obs[-1].speed_m_s * 50e-6)
    expected = 0.4 * 200.0 * 50e-6 * (len(obs) - 1 + frac)
    assert obs[-1].energy_absorbed_j == pytest.approx(expected, rel=0.03)
    assert max(abs(o.energy_error_pct) for o in obs) < 1e-6
