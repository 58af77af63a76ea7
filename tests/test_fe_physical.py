"""The physical plant's models: consolidation in mass coordinates, keyhole onset, absorptivity by
surface, thermal-history outputs, the AM-Bench cases and the presets."""
import math
from dataclasses import replace

import numpy as np
import pytest

from fe_node.am_bench import CASES
from fe_node.keyhole import beam_1e2_radius_m, cavity_absorptivity, drill, keyhole_temperature_k, vapour_depth_m
from fe_node.observe import bilinear_at, interp_matrix, trailing_edge
from fe_node.presets import PHYSICAL, calibrated, preset
from fe_node.scan import ScanPlan
from fe_node.scenarios import scenario
from fe_node.settings import Settings
from fe_node.solver import ThermalModel, explicit_update

COARSE = dict(h_fine_m=40e-6, margin_m=0.5e-3, depth_m=0.6e-3, fine_pad_m=120e-6,
              fine_depth_m=160e-6, h_max_m=0.2e-3)


def run(n_steps=30, power_w=250.0, **kw):
    model = ThermalModel(Settings(**COARSE, **kw), ScanPlan.single(1.2e-3))
    return model, [model.step(power_w, 0.8) for _ in range(n_steps)]


@pytest.fixture(scope="module")
def keyhole_run():
    return run(keyhole=True)


def test_keyhole_temperature_from_the_recoil_balance():
    # 0.54 p_sat(T) = p_amb + 2 gamma / w, with w the 1/e² radius of the eq. 6 beam
    assert beam_1e2_radius_m(50e-6) == pytest.approx(40.82e-6, rel=1e-3)
    t = keyhole_temperature_k(50e-6, 3190.0)
    assert 3400 < t < 3500
    assert keyhole_temperature_k(100e-6, 3190.0) < t          # a wider depression needs less recoil


def test_drill_conserves_energy_and_caps_the_surface():
    rng = np.random.default_rng(0)
    h = rng.uniform(1e9, 5e9, (4, 6, 5))
    h[:, -1, :] = rng.uniform(1e9, 2e10, (4, 5))
    m = rng.uniform(0.5, 2.0, h.shape)
    e0 = float(np.sum(m * h))
    opening = drill(h, m, 6e9)
    assert float(np.sum(m * h)) == pytest.approx(e0, rel=1e-13)
    assert np.all(h[:, -1, :] <= 6e9) and opening.any() and np.all(h[:, 1:, :] <= 6e9 * (1 + 1e-12))


def _drill_numpy(h, m, h_cap, n_heated):
    """The vectorised form of ``drill``: every column of the opening walked down together."""
    nz = h.shape[1]
    j, i = np.nonzero(np.any(h[:, nz - n_heated:, :] > h_cap, axis=1))
    excess = np.zeros(len(j))
    for k in range(nz - 1, -1, -1):
        total = excess + (h[j, k, i] - h_cap) * m[j, k, i]
        full = total > 0
        h[j, k, i] = np.where(full, h_cap, h_cap + total / m[j, k, i])
        excess = np.where(full, total, 0.0)
        if k <= nz - n_heated and not np.any(excess > 0):
            break
    h[j, 0, i] += excess / m[j, 0, i]


@pytest.mark.parametrize("n_heated", [1, 2])
def test_drill_equals_the_vectorised_form(n_heated):
    """Column by column (compiled) as all columns at once (numpy), to rounding: the columns that carry
    no excess are left as they are instead of rewritten as ``h_cap + (h - h_cap) m / m``."""
    rng = np.random.default_rng(3)
    h = rng.uniform(1e9, 5.9e9, (9, 12, 11))
    h[:, -n_heated:, :] = rng.uniform(1e9, 3e10, (9, n_heated, 11))
    m = rng.uniform(0.5, 2.0, h.shape)
    ref = h.copy()
    _drill_numpy(ref, m, 6e9, n_heated)
    drill(h, m, 6e9, n_heated)
    np.testing.assert_allclose(h, ref, rtol=1e-15, atol=0)


def test_cavity_absorptivity_rises_with_keyhole_depth():
    # Gouffé without its correction term: a / (a (1 - s/S) + s/S), s/S = r / (r + 2 d)
    r = 40e-6
    assert cavity_absorptivity(0.3, 0.0, r) == pytest.approx(0.3)               # no keyhole: the flat surface
    assert cavity_absorptivity(0.3, r, r) == pytest.approx(0.3 / (0.3 * 2 / 3 + 1 / 3))
    a = cavity_absorptivity(0.3, np.array([0.0, 0.5, 1.0, 2.0, 5.0, 50.0]) * r, r)
    assert np.all(np.diff(a) > 0) and 0.97 < a[-1] < 1.0                       # -> 1 for a deep cavity
    assert cavity_absorptivity(1.0, 3 * r, r) == pytest.approx(1.0)


def test_vapour_depth_counts_the_share_between_boiling_and_onset():
    h = np.array([[1.0, 2.0, 3.0, 4.0, 9.0], [9.0, 9.0, 9.0, 9.0, 9.0]]).T[None]     # (1, 5, 2): two columns
    m = np.full(h.shape, 4.0)
    a_top = np.array([[2.0, 2.0]])
    # boiling at 2, onset at 4: shares 0, 0, 0.5, 1, 1 (clipped) of 4 m³ over 2 m²
    assert vapour_depth_m(h, m, a_top, 2.0, 4.0, np.array([[1.0, 0.0]])) == pytest.approx(2.5 * 4.0 / 2.0)
    assert vapour_depth_m(h, m, a_top, 2.0, 4.0, np.array([[1.0, 1.0]])) == pytest.approx((5.0 + 10.0) / 2)
    assert vapour_depth_m(h, m, a_top, 10.0, 12.0, np.array([[1.0, 1.0]])) == 0.0


def test_keyhole_depth_raises_the_absorbed_power(keyhole_run):
    """The keyhole's depth follows its vapour under the beam, and the beam absorbs the cavity's
    absorptance (one value for the whole beam); below keyhole onset both are the flat surface's."""
    model, obs = keyhole_run
    s = model.settings
    d = model.keyhole_depth_m()
    assert 20e-6 < d < 400e-6
    a = model.absorptivity()
    assert a == pytest.approx(cavity_absorptivity(s.absorptivity, d, model.keyhole_radius_m))
    assert a > 1.2 * s.absorptivity
    cold, cold_obs = run(power_w=60.0, keyhole=True)
    assert cold.keyhole_depth_m() == 0.0 and cold.absorptivity() == pytest.approx(s.absorptivity)
    assert obs[-1].energy_absorbed_j > 1.2 * s.absorptivity * 250.0 * model.time_s


def test_keyhole_caps_the_surface_and_drills_deeper(keyhole_run):
    model, obs = keyhole_run
    _, bare = run()
    assert max(o.t_peak_k for o in bare) > 1e4
    assert max(o.t_peak_k for o in obs) <= model.t_keyhole_k * (1 + 1e-9)
    assert obs[-1].depth_m > 1.2 * bare[-1].depth_m
    assert max(abs(o.energy_error_pct) for o in obs) < 1e-6


def test_evaporation_is_a_counted_loss(keyhole_run):
    _, dry = keyhole_run
    _, wet = run(keyhole=True, evaporation=True)
    assert wet[-1].energy_lost_j > 1.5 * dry[-1].energy_lost_j
    assert max(abs(o.energy_error_pct) for o in wet) < 1e-6


def test_consolidation_to_dense_metal_in_mass_coordinates():
    model, obs = run(powder_layer_m=40e-6, keyhole=True)
    assert model.grid.zs[-1] == pytest.approx(40e-6)          # the layer's dense height
    pb = model.powder
    assert pb.consolidated.sum() > 20
    kw = model.operator.kw.reshape(pb.consolidated.shape[0], -1, pb.consolidated.shape[2])[:, pb.k0:, :]
    assert np.all(kw[pb.consolidated] == 1.0) and np.all(kw[~pb.consolidated] == pytest.approx(pb.kw_powder))
    assert np.all(model.operator.rho_w == 1.0)                # powder holds the dense mass
    assert max(abs(o.energy_error_pct) for o in obs) < 1e-6
    # the track is dense behind the laser, powder elsewhere: absorptivity by surface
    a = model.surface_absorptivity()
    s = model.settings
    assert sorted((a.min(), a.max())) == pytest.approx(sorted((s.absorptivity, s.powder_absorptivity)))
    ny, nx = a.shape
    assert a[ny // 2, nx // 2] == pytest.approx(s.absorptivity)     # on the track, behind the laser
    # a molten top node is melt before its elements consolidate
    j, i = np.unravel_index(np.argmax(a == s.powder_absorptivity), a.shape)
    model._h[j, -1, i] = model.law.enthalpy(s.material.t_liquidus + 1.0)
    assert model.surface_absorptivity()[j, i] == pytest.approx(s.absorptivity)
    # the beam absorbs the surface's absorptivity averaged under it, raised by the keyhole's cavity
    d, r = model.keyhole_depth_m(), model.keyhole_radius_m
    beam = model.absorptivity()
    lo, hi = sorted((s.absorptivity, s.powder_absorptivity))
    assert cavity_absorptivity(lo, d, r) < beam < cavity_absorptivity(hi, d, r)


def test_thermal_history_outputs(keyhole_run):
    _, obs = keyhole_run
    o = obs[-1]
    assert 1e5 < o.thermal_gradient_k_m < 1e8          # LPBF: 1e6-1e7 K/m
    assert o.solidification_rate_m_s == pytest.approx(0.8)
    assert o.cooling_rate_k_s == pytest.approx(o.thermal_gradient_k_m * 0.8)
    # the mushy zone of a linear field along the scan line: its slope
    xs, ys = np.linspace(-1e-3, 1e-3, 41), np.linspace(-0.2e-3, 0.2e-3, 9)
    t = 2000.0 + 1e6 * xs[:, None] + 0 * ys[None, :]        # 1e6 K/m: liquidus at x = -0.377 mm
    g = trailing_edge(t, xs, ys, np.array([0.0, 0.0]), np.array([1.0, 0.0]), 1623.0, 1563.0, 0.6e-3, 5e-6)
    assert g == pytest.approx(1e6, rel=1e-9)
    assert trailing_edge(t, xs, ys, np.array([0.0, 0.0]), np.array([1.0, 0.0]), 1623.0, 1563.0, 0.4e-3, 5e-6) == 0
    # its samples: the bilinear interpolant (the dense interpolation matrices), clamped outside
    rng = np.random.default_rng(10)
    field, px, py = rng.standard_normal((41, 9)), rng.uniform(-1.2e-3, 1.2e-3, 50), rng.uniform(-0.3e-3, 0.3e-3, 50)
    dense = np.einsum("pi,ij,pj->p", interp_matrix(xs, px), field, interp_matrix(ys, py))
    assert np.allclose(bilinear_at(field, xs, ys, px, py), dense, rtol=0, atol=1e-14)


def test_am_bench_beams_and_cases():
    assert len(CASES) == 6
    ammt = CASES[0]
    # eq. 6 radius of a 170 µm D4σ spot: exp(-3 r²/r_s²) = exp(-2 r²/w²), w = 85 µm
    assert math.exp(-3 * 85e-6 ** 2 / ammt.beam_radius_m ** 2) == pytest.approx(math.exp(-2))


def test_presets():
    assert preset("bare-plate") == {}
    phys = preset("physical")
    assert phys == {**PHYSICAL, **calibrated()}
    s = scenario("single-track", preset="physical", n_tracks=1).settings
    assert s.keyhole and s.evaporation and s.powder_layer_m == 25e-6
    assert s.liquid_k_factor_xy == calibrated()["liquid_k_factor_xy"]
    assert scenario("single-track", preset="physical", evaporation=False).settings.evaporation is False
    with pytest.raises(ValueError, match="preset must be one of"):
        scenario("single-track", preset="rough")


def test_the_default_plant_is_physical_and_the_bare_plate_is_the_bare_settings():
    """Every plant built without a preset (launch.py, the plant node, ``python -m fe_node``) is the
    physical one; ``preset = "bare-plate"`` (docs/bare-plate.toml) is ``Settings()`` exactly."""
    from fe_node.cli import plant_table
    from fe_node.presets import DEFAULT
    from fe_node.settings import Settings
    from tests.plants import BARE_CONFIG

    assert DEFAULT == "physical"
    for name in ("layer", "double-track", "ident-layer"):
        assert scenario(name).settings == scenario(name, preset="physical").settings != Settings()
        assert scenario(name, **plant_table(BARE_CONFIG)).settings == Settings()


def test_validate_names_each_failed_check(monkeypatch, capsys):
    """``python -m fe_node validate`` exits 1 naming every figure outside its limit (0 when all hold)."""
    import fe_node.validate as v
    from fe_node.cli import main

    good = {k: 0.5 * (lo + hi) for k, (lo, hi) in v.CHECKS.items()}
    assert v.failures(good) == []
    bad = dict(good, peak_temperature_k=4689.0, am_bench_width_error_pct=31.0)
    assert [f.split(" =")[0] for f in v.failures(bad)] == ["peak_temperature_k", "am_bench_width_error_pct"]
    for report, status in ((good, 0), (bad, 1)):
        monkeypatch.setattr(v, "validate", lambda s, progress=False, r=report: dict(
            r, passed=not v.failures(r), failed=v.failures(r)))
        assert main(["validate", "--json"]) == status
    err = capsys.readouterr().err
    assert "FAILED: peak_temperature_k = 4689 outside [0, 3500]; am_bench_width_error_pct = 31" in err


def test_run_and_validate_take_the_plant_table(tmp_path, capsys):
    """``run --config`` applies ``[plant]`` (powder off here) and reports width and depth; a bad key is
    one line naming it, exit 2."""
    import json

    from fe_node.cli import main

    bare = tmp_path / "bare.toml"
    bare.write_text('[plant]\npowder_layer_m = 0.0\nh_fine_m = 40e-6\ntrack_length_m = 1e-3\n')
    assert main(["run", "--scenario", "single-track", "--power-w", "180", "--speed-mm-s", "800",
                 "--config", str(bare), "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["width_um"] > 50 and res["depth_um"] > 10
    wrong = tmp_path / "wrong.toml"
    wrong.write_text('[plant]\nabsorptivity = 2.0\n')
    for command in ("run", "validate"):
        assert main([command, "--config", str(wrong), "--json"]) == 2
        assert "absorptivity must be in (0, 1]" in capsys.readouterr().err


@pytest.mark.slow
def test_validate_on_the_physical_preset_and_with_a_wrong_absorptivity(tmp_path):
    """The whole check on the physical preset; with ``absorptivity = 0.2`` it names the AM-Bench checks."""
    import json
    import subprocess
    import sys

    low = tmp_path / "low.toml"
    low.write_text('[plant]\npreset = "physical"\nabsorptivity = 0.2\n')
    p = subprocess.run([sys.executable, "-m", "fe_node", "validate", "--config", str(low), "--json"],
                       capture_output=True, text=True, timeout=3600)
    assert p.returncode == 1, p.stderr[-2000:]
    assert "am_bench_width_error_pct" in p.stderr
    report = json.loads(p.stdout.strip().splitlines()[-1])
    assert report["passed"] is False and report["am_bench_width_error_pct"] > 10


def test_the_shipped_calibration_record_is_what_the_plant_computes():
    """The record's residuals are reproduced by the plant as it is (one case, the shortest): a change
    of the physics that moves the calibrated pools makes the record stale, and this fails until
    ``python -m fe_node calibrate`` is run again."""
    import json

    from fe_node.calibrate import case_errors
    from fe_node.presets import CALIBRATION_PATH

    record = json.loads(CALIBRATION_PATH.read_text())
    case = next(c for c in CASES if c.name == "AMMT-C")
    row = next(r for r in record["cases"] if r["case"] == "AMMT-C")
    settings = scenario("single-track", preset="physical").settings
    got = case_errors(settings, (case,))[0]
    assert got["width_um"] == pytest.approx(row["width_um"], rel=1e-6)
    assert got["depth_um"] == pytest.approx(row["depth_um"], rel=1e-6)


@pytest.mark.parametrize("operator", ["tensor", "csr"])
def test_liquid_factors_on_the_mushy_box_equal_the_full_arrays(operator):
    """explicit_update evaluates psi and K_z only on the box of nodes above the solidus: the same
    update as psi and K_z on the whole grid."""
    model, _ = run(12, powder_layer_m=40e-6, liquid_k_factor_xy=1.3, liquid_k_factor_z=2.2, operator=operator)
    h0, law, op = model._h.copy(), model.law, model.operator
    psi = law.mushy_integral(h0)
    assert 0 < np.count_nonzero(psi) < 0.01 * psi.size      # a small pool: the box is a small part
    top = np.random.default_rng(9).uniform(0.0, 1.0, model._c_top.shape)
    f_xy, f_z = 1.3, 2.2
    ref = h0 - model._c * (op(law.kirchhoff(h0) + (f_xy - 1) * psi) + op.vertical((f_z - f_xy) * psi))
    ref[:, -1, :] += top * model._c_top
    h = h0.copy()
    explicit_update(h, op, law, model._c, top, model._c_top, (f_xy, f_z))
    assert np.max(np.abs(h - ref)) <= 1e-13 * np.max(np.abs(ref - h0))


def physical_track_area(h_fine_m: float, track_m: float) -> float:
    """Top-surface pool area [m²] (mean of the last 5 steps) of a single track (250 W, 800 mm/s) on
    the physical preset at fine size ``h_fine_m`` [m], on a small domain."""
    s = replace(scenario("single-track", preset="physical").settings, h_fine_m=h_fine_m, margin_m=0.3e-3,
                depth_m=0.5e-3)
    model = ThermalModel(s, ScanPlan.single(track_m))
    obs = []
    while not model.done:
        obs.append(model.step(250.0, 0.8))
    return float(np.mean([o.area_m2 for o in obs[-5:]]))


def test_the_physical_surface_physics_converges_with_the_mesh():
    """Evaporation, keyhole onset, cavity absorptance, powder: the pool of a 1.5 mm track (about steady:
    at 1 mm its tail still grows, faster on the coarse mesh) at 25 µm within 1.5 % of the one at
    12.5 µm (validate's ``mesh_convergence_pct`` limit).  With a per-node keyhole absorptivity it was
    5.7 % off at 1 mm, with each node's surface absorptivity under one cavity factor 4.8 % (docs/fe.md,
    Measured)."""
    a_h, a_h2 = physical_track_area(25e-6, 1.5e-3), physical_track_area(12.5e-6, 1.5e-3)
    assert abs(a_h / a_h2 - 1) < 0.015, (a_h, a_h2)


@pytest.mark.slow
def test_the_physical_plant_passes_mesh_convergence_of_validate():
    """The full check: validate's 3 mm track on the physical preset at 25 and 12.5 µm."""
    from fe_node.validate import CHECKS, track

    s = scenario("single-track", preset="physical").settings
    a_h, a_h2 = track(s)[0], track(replace(s, h_fine_m=s.h_fine_m / 2))[0]
    lo, hi = CHECKS["mesh_convergence_pct"]
    assert lo <= 100 * (a_h - a_h2) / a_h2 <= hi
