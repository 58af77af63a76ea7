"""The pool's build-up after laser-on or a layer start, which the models are not fitted on, and the
sample counts that were chosen at the FE step and scale with a model's sample period.

Kept apart from :mod:`gp_model.narx` so that a controller's settings can name it without loading
the model's numerics (scipy, numba).
"""

from __future__ import annotations

import math

BUILD_UP_STEPS = 20
"""Samples whose target lies in the first 20 steps after laser-on or a layer start (the pool builds
up) are neither fitted nor judged; the preview MPC's observer starts after them."""

REFERENCE_PERIOD_S = 50e-6
"""The sample period [s] at which the models' and the preview MPC's sample counts were chosen (the FE
step): a model at another period (a camera's frame period) takes them as the same time, :func:`steps_at`."""


def steps_at(steps: int, sample_period_s: float, minimum: int = 1) -> int:
    """``steps`` samples chosen at :data:`REFERENCE_PERIOD_S`, as samples at ``sample_period_s`` [s]: the
    same count at the reference period (within 1 %), else the same time rounded up, at least ``minimum``."""
    ratio = sample_period_s / REFERENCE_PERIOD_S
    if abs(ratio - 1.0) <= 0.01:
        return steps
    return max(minimum, math.ceil(steps / ratio - 1e-9))


def build_up_steps(sample_period_s: float) -> int:
    """Samples of the pool's build-up at ``sample_period_s`` [s]: :data:`BUILD_UP_STEPS` as time (1 ms)."""
    return steps_at(BUILD_UP_STEPS, sample_period_s)


ROLLOUT_HORIZON = 40
"""Steps of the held-out rollout that selects a model, and of the T-ahead forecast its persistence is
fitted on, at the reference period (2 ms)."""
FRAME_HORIZON_MIN = 8
"""The rollout horizon at a longer sample period, at least: 8 frames (8 ms at 1 ms) reach past the
next turnaround (a 10 mm track at 0.8 m/s is 12.5 ms), which 2 ms (2 frames) would not."""
ROLLOUT_STRIDE = 5
"""Steps between the starts of the rollouts at the reference period (as time: every frame at 1 ms)."""


def rollout_horizon(sample_period_s: float) -> int:
    """:data:`ROLLOUT_HORIZON` at ``sample_period_s`` [s] (:func:`steps_at`, at least :data:`FRAME_HORIZON_MIN`)."""
    return steps_at(ROLLOUT_HORIZON, sample_period_s, FRAME_HORIZON_MIN)
