"""Free-running GP-surrogate plant: ``python -m fe_node.surrogate --rate-hz R``.

A sensor-like plant for timing the closed loop without the FE solver: each tick it steps the
shipped GP model's posterior mean, ``x[k+1] = mean(x[k], T[k], p, v)``, with a per-track
temperature-ahead profile (heat accumulating along each track and from track to track), and
publishes ``MeltPoolState`` (``source="surrogate"``) at ``--rate-hz`` without waiting for the
controller. It applies the newest command it has and counts the steps whose command arrived
after the next publish as deadline misses; it measures the round trip state → command
(``--json`` prints the summary; ``benchmarks/bench_loop.py`` uses it). Process time advances
by the GP's step (50 µs) per tick, whatever the wall rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fe_node.freerun import PlantSample, add_free_run_arguments, serve, settings_from_args
from gp_model.files import load_for_node
from gp_model.model import GPModel
from gp_model.shipped import ONE_STEP_MODEL_PATH
from messages.bus import parse_node_arguments, single_threaded_blas
from messages.cli import ArgumentParser, UsageError, exit_usage, run_main

NODE_NAME = "plant"
GP_STEP_S = 50e-6  # the time step of the FE data the GP was trained on [s]


@dataclass(frozen=True)
class TrackProfile:
    """Temperature ahead of the spot along a bidirectional layer (SI).

    ``T = t0_k + track_rise_k · min(track, 10) / 10 + along_rise_k · (1 - exp(-s / along_scale_m))``,
    ``s`` the distance along the current track.
    """

    t0_k: float = 300.0
    track_rise_k: float = 300.0
    along_rise_k: float = 500.0
    along_scale_m: float = 1.0e-3
    track_length_m: float = 4.0e-3
    hatch_m: float = 1.0e-4

    def at(self, distance_m: float) -> PlantSample:
        """Position, direction, track and ``t_ahead_k`` after ``distance_m`` of scanning (area 0)."""
        track, along = divmod(distance_m, self.track_length_m)
        k = int(track)
        forward = k % 2 == 0
        t_ahead = (self.t0_k + self.track_rise_k * min(k, 10) / 10
                   + self.along_rise_k * (1.0 - math.exp(-along / self.along_scale_m)))
        return PlantSample(area_m2=0.0, t_ahead_k=t_ahead, x_m=along if forward else self.track_length_m - along,
                           y_m=k * self.hatch_m, direction=(1.0, 0.0) if forward else (-1.0, 0.0), track=k)


class GPSurrogate:
    """The GP mean as a one-step plant (area clipped at 0; a history model gets the last change)."""

    def __init__(self, model, profile: TrackProfile, area0_m2: float = 0.05e-6) -> None:
        self.model, self.profile = model, profile
        self.distance_m = 0.0
        self.area_m2 = self.previous_area_m2 = area0_m2
        self._z = np.zeros(getattr(model, "n_inputs", 4))

    def _sample(self) -> PlantSample:
        at = self.profile.at(self.distance_m)
        return PlantSample(self.area_m2, at.t_ahead_k, at.x_m, at.y_m, at.direction, at.track)

    def initial(self) -> PlantSample:
        """The state before the first step."""
        return self._sample()

    def step(self, power_w: float, speed_m_s: float, dt_s: float) -> PlantSample:
        """One GP step at ``power_w`` [W], ``speed_m_s`` [m/s]; the spot moves ``speed · dt_s``."""
        z = self._z
        z[0], z[1], z[2], z[3] = self.area_m2, self.profile.at(self.distance_m).t_ahead_k, power_w, speed_m_s
        if z.shape[0] == 5:
            z[4] = self.area_m2 - self.previous_area_m2
        mean, _ = self.model.mean_and_jacobian(z)
        self.previous_area_m2, self.area_m2 = self.area_m2, max(mean, 0.0)
        self.distance_m += speed_m_s * dt_s
        return self._sample()


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m fe_node.surrogate``."""
    parser = ArgumentParser(prog="python -m fe_node.surrogate", description=__doc__.split("\n\n")[0])
    add_free_run_arguments(parser, rate_hz=2000.0)
    parser.add_argument("--model", type=Path, default=ONE_STEP_MODEL_PATH,
                        help="GP model file (default: the shipped one)")
    single_threaded_blas()
    try:
        args, bus_settings = parse_node_arguments(parser, argv)
        settings, policy = settings_from_args(args, dt_s=GP_STEP_S)
        model = load_model(args.model)
    except UsageError as err:
        return exit_usage(parser.prog, err)
    profile = TrackProfile()
    return serve(NODE_NAME, GPSurrogate(model, profile), bus_settings, args, settings, policy,
                 {"model": str(args.model), "profile": vars(profile), "dt_s": GP_STEP_S}, source="surrogate")


def load_model(path: Path) -> GPModel:
    """The GP model at ``path`` (:class:`UsageError` with a one-line reason if it cannot be loaded)."""
    return load_for_node(GPModel, path)


if __name__ == "__main__":
    run_main(main)
