"""Example sensor node: a fake melt-pool camera, ``python -m fe_node.example_sensor``.

The smallest hardware-shaped plant: it publishes ``MeltPoolState`` (``source="sensor"``) at a
fixed rate from a synthetic first-order melt-pool model and applies the newest admitted
``LaserCommand`` (its own power/speed bounds, a step it can use; every other command is dropped
and counted), and the safe power as soon as the controller's liveliness token is gone or after
``--command-timeout-s`` without commands, exactly as a camera + laser driver would. Replace
:class:`SyntheticMeltPool` by frame grabbing and a laser driver call and the rest of the
contract stays; see ``docs/node-contract.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fe_node.freerun import PlantSample, add_free_run_arguments, serve, settings_from_args
from messages.bus import parse_node_arguments, single_threaded_blas
from messages.cli import ArgumentParser, UsageError, exit_usage, run_main

NODE_NAME = "plant"


@dataclass(frozen=True)
class SyntheticSettings:
    """Synthetic melt-pool model (SI).

    Attributes
    ----------
    area_ref_m2 : float
        Steady area at ``power_ref_w``, ``speed_ref_m_s`` and ``t0_k`` [m²].
    power_ref_w : float
        Reference power [W].
    speed_ref_m_s : float
        Reference speed [m/s].
    tau_s : float
        Time constant of the area's first-order response [s].
    t0_k : float
        Powder-bed temperature [K].
    preheat_k : float
        Temperature rise ahead of the spot along a track [K] (heat accumulation).
    track_length_m, hatch_m : float
        Bidirectional scan: track length and spacing [m].
    """

    area_ref_m2: float = 0.063e-6
    power_ref_w: float = 250.0
    speed_ref_m_s: float = 0.8
    tau_s: float = 2.0e-4
    t0_k: float = 300.0
    preheat_k: float = 400.0
    track_length_m: float = 4.0e-3
    hatch_m: float = 1.0e-4

    def __post_init__(self) -> None:
        for name in ("area_ref_m2", "power_ref_w", "speed_ref_m_s", "tau_s", "t0_k", "track_length_m", "hatch_m"):
            if not math.isfinite(getattr(self, name)) or getattr(self, name) <= 0:
                raise UsageError(f"{name} must be finite and > 0")


class SyntheticMeltPool:
    """First-order melt pool: area → ``a_ref · P/P_ref · sqrt(v_ref/v) · (1 + (T - T0)/2000 K)``."""

    def __init__(self, settings: SyntheticSettings) -> None:
        self.s = settings
        self.distance_m = 0.0
        self.area_m2 = 0.0

    def _sample(self) -> PlantSample:
        s = self.s
        track, along = divmod(self.distance_m, s.track_length_m)
        forward = int(track) % 2 == 0
        t_ahead = s.t0_k + s.preheat_k * (1.0 - math.exp(-along / (0.25 * s.track_length_m)))
        return PlantSample(
            area_m2=self.area_m2, t_ahead_k=t_ahead, x_m=along if forward else s.track_length_m - along,
            y_m=int(track) * s.hatch_m, direction=(1.0, 0.0) if forward else (-1.0, 0.0), track=int(track),
        )

    def initial(self) -> PlantSample:
        """The observation before the first step (no melt pool yet)."""
        return self._sample()

    def step(self, power_w: float, speed_m_s: float, dt_s: float) -> PlantSample:
        """Advance by ``dt_s`` [s] at ``power_w`` [W], ``speed_m_s`` [m/s]."""
        s = self.s
        t_ahead = self._sample().t_ahead_k
        steady = (s.area_ref_m2 * power_w / s.power_ref_w * math.sqrt(s.speed_ref_m_s / speed_m_s)
                  * (1.0 + (t_ahead - s.t0_k) / 2000.0))
        self.area_m2 += (steady - self.area_m2) * (1.0 - math.exp(-dt_s / s.tau_s))
        self.distance_m += speed_m_s * dt_s
        return self._sample()


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m fe_node.example_sensor``."""
    parser = ArgumentParser(prog="python -m fe_node.example_sensor", description=__doc__.split("\n\n")[0])
    add_free_run_arguments(parser, rate_hz=1000.0)
    single_threaded_blas()
    try:
        args, bus_settings = parse_node_arguments(parser, argv)
        settings, policy = settings_from_args(args)
        model = SyntheticSettings()
    except UsageError as err:
        return exit_usage(parser.prog, err)
    return serve(NODE_NAME, SyntheticMeltPool(model), bus_settings, args, settings, policy,
                 {"model": "synthetic first-order", **vars(model)}, source="sensor")


if __name__ == "__main__":
    run_main(main)
