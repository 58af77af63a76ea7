"""Eagar-Tsai reference and FE agreement, scenarios, CLI behaviour (fe_node)."""
import json

import numpy as np
import pytest

from fe_node.eagar_tsai import EagarTsai, EagarTsaiCase
from fe_node.scenarios import NAMES, PART_NAMES, scenario
from fe_node.settings import Settings
from fe_node.validate import fe_eagar_tsai_area
from tests import forked_cli


@pytest.fixture(scope="module")
def et_geometry():
    return EagarTsai(EagarTsaiCase()).geometry()


def test_eagar_tsai_matches_anchor_numbers(et_geometry):
    # Eagar & Tsai, Welding J. 62 (1983) 346s, for this case, evaluated independently (docs/fe.md,
    # "Material data and sources"): area 0.0692 mm², length 626 µm, width 136 µm, depth 62 µm
    g = et_geometry
    assert g["area_m2"] * 1e6 == pytest.approx(0.0692, rel=5e-3)
    assert g["length_m"] * 1e6 == pytest.approx(626, rel=5e-3)
    assert g["width_m"] * 1e6 == pytest.approx(136, rel=2e-2)
    assert g["depth_m"] * 1e6 == pytest.approx(62, rel=2e-2)


def test_eagar_tsai_centre_temperature_scales_with_power():
    e1 = EagarTsai(EagarTsaiCase(power_w=100.0))
    e2 = EagarTsai(EagarTsaiCase(power_w=200.0))
    d1 = e1.temperature(-2e-5, 0.0, 0.0) - 300.0
    d2 = e2.temperature(-2e-5, 0.0, 0.0) - 300.0
    assert d2 == pytest.approx(2 * d1, rel=1e-12) and d1 > 0


def test_fe_agrees_with_eagar_tsai_on_coarse_mesh(et_geometry):
    fe = fe_eagar_tsai_area(EagarTsaiCase(), h_fine_m=40e-6, track_m=2.4e-3)
    assert fe == pytest.approx(et_geometry["area_m2"], rel=0.09)   # +7.2 % at 40 µm (3 sub-steps)


def test_fe_agrees_with_eagar_tsai_default_mesh(et_geometry):
    fe = fe_eagar_tsai_area(EagarTsaiCase(), h_fine_m=25e-6)
    assert fe == pytest.approx(et_geometry["area_m2"], rel=0.03)   # +2.7 % at 25 µm, +0.3 % at 12.5 µm


@pytest.mark.slow
def test_mesh_convergence_default_vs_half(et_geometry):
    fe = fe_eagar_tsai_area(EagarTsaiCase(), h_fine_m=25e-6)
    fine = fe_eagar_tsai_area(EagarTsaiCase(), h_fine_m=12.5e-6)
    assert fe == pytest.approx(fine, rel=0.03)   # +2.39 % since 3 sub-steps per step (`python -m fe_node validate`)
    assert abs(fine - et_geometry["area_m2"]) < abs(fe - et_geometry["area_m2"])   # refining approaches Eagar-Tsai


def test_table2_geometry():
    for k, hatch in zip(range(5, 10), (0.1, 0.15, 0.05, 0.1, 0.1)):
        sc = scenario(f"table2-case{k}")
        (a0, a1), (b0, b1) = sc.plan.tracks
        assert len(sc.plan.tracks) == 2 and sc.plan.lengths == pytest.approx([5e-3, 5e-3])
        assert b0[1] - a0[1] == pytest.approx(hatch * 1e-3)
        assert b0 == pytest.approx((a1[0], b0[1])) and b1[0] == a0[0]   # serpentine
    for k in range(1, 5):
        sc = scenario(f"table2-case{k}")
        assert len(sc.plan.tracks) == 1 and sc.plan.total_length == pytest.approx(5e-3)
    layer = scenario("layer")
    assert layer.plan.lengths == pytest.approx([10e-3] * 4)
    # 12.5 ms per track at 800 mm/s: track changes after 250 steps
    k, _, _ = layer.plan.locate(np.array([249, 251, 501, 751]) * 0.8 * 50e-6)
    assert list(k) == [0, 1, 2, 3]


def test_profiles_stay_in_process_window():
    for name in (n for n in NAMES if n not in PART_NAMES):  # parts: tests/test_fe_part.py (needs PySLM)
        sc = scenario(name)
        p = [sc.profile.command(i) for i in range(400)]
        # ident-* staircases leave the 150-300 W window by design (250 +- 60 W; tests/test_identify.py)
        p_lo, p_hi = (0.0, 350.0) if name.startswith("ident-") else (150.0, 300.0)
        assert all(p_lo <= pw <= p_hi and 0.6 <= v <= 1.0 for pw, v in p)
    assert scenario("table2-case2").profile.command(10)[0] != scenario("table2-case2").profile.command(0)[0]


@pytest.mark.parametrize("kw", [dict(power_w=-1.0), dict(speed_m_s=0.0), dict(hatch_m=0.0),
                                dict(h_fine_m=80e-6), dict(absorptivity=1.5), dict(foo=1)])
def test_bad_settings_raise_value_error(kw):
    with pytest.raises(ValueError):
        scenario("double-track", **kw)


def test_unknown_scenario():
    with pytest.raises(ValueError, match="unknown scenario"):
        scenario("nope")
    with pytest.raises(ValueError, match="mesh too coarse"):
        Settings(h_fine_m=60e-6)


def _cli(*args):
    return forked_cli.run("-m", "fe_node", *args)


@pytest.mark.parametrize("args", [("run", "--power-w", "-5"), ("run", "--speed-mm-s", "0"),
                                  ("run", "--scenario", "bogus"), ("run", "--h-um", "100"),
                                  ("run", "--power-w", "abc"), ("validate", "--h-um", "-1")])
def test_cli_bad_parameters_exit_2_one_line(args):
    p = _cli(*args)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in p.stderr


def test_cli_run_single_track_json():
    p = _cli("run", "--scenario", "single-track", "--power-w", "250", "--speed-mm-s", "800",
             "--h-um", "40", "--json")
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout.strip().splitlines()[-1])
    for key in ("area_mm2", "width_um", "length_um", "depth_um"):
        assert res[key] > 0
    assert 0.03 < res["area_mm2"] < 0.12
