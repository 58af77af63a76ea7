"""Open-loop driving of a scenario and summaries of its observations."""
from __future__ import annotations

import numpy as np
from tqdm import tqdm

from fe_node.multilevel import plant_model
from fe_node.observe import Observation
from fe_node.scenarios import Scenario


def run_open_loop(sc: Scenario, progress: bool = False) -> list[Observation]:
    """Run ``sc`` with its open-loop profile until the plan is done.

    Returns the observations after each step (step 1 ... N).  ``progress`` shows a tqdm
    bar on stderr.
    """
    model = plant_model(sc.settings, sc.plan, sc.layer_plans)
    plans = sc.layer_plans or (sc.plan,) * sc.settings.n_layers
    n_est = int(np.ceil(sum(p.total_length for p in plans) / (sc.profile.speed_m_s.range()[0] * sc.settings.dt_s)))
    out = []
    with tqdm(total=n_est, disable=not progress, unit="step", leave=False) as bar:
        while not model.done:
            out.append(model.step(*sc.profile.command(model.step_index)))
            bar.update()
    return out


def quasi_steady(obs: list[Observation], fraction: float = 0.2) -> dict:
    """Mean melt pool over the last ``fraction`` of the steps of the last track.

    Returns a dict with area_mm2, width_um, length_um, depth_um,
    cross_section_mm2, t_peak_k, n_steps and the steps' energy error.
    """
    last = [o for o in obs if o.track == obs[-1].track]
    tail = last[-max(1, int(round(fraction * len(last)))):]

    def mean(attr, scale):
        return float(np.mean([getattr(o, attr) for o in tail]) * scale)

    return dict(area_mm2=mean("area_m2", 1e6), width_um=mean("width_m", 1e6),
                length_um=mean("length_m", 1e6), depth_um=mean("depth_m", 1e6),
                cross_section_mm2=mean("cross_section_m2", 1e6),
                t_peak_k=mean("t_peak_k", 1.0), n_steps=len(obs),
                energy_error_pct=float(obs[-1].energy_error_pct))


def summary(obs: list[Observation]) -> dict:
    """Min / mean / max of area [mm²], T-ahead [K] and commands over a whole run."""
    def stats(values):
        v = np.asarray(values)
        return dict(min=float(v.min()), mean=float(v.mean()), max=float(v.max()))

    return dict(n_steps=len(obs), time_s=obs[-1].time_s,
                area_mm2=stats([o.area_m2 * 1e6 for o in obs]),
                t_ahead_k=stats([o.t_ahead_k for o in obs]),
                power_w=stats([o.power_w for o in obs]),
                speed_mm_s=stats([o.speed_m_s * 1e3 for o in obs]),
                energy_error_pct=float(max(abs(o.energy_error_pct) for o in obs)))
