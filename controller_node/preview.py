"""Scan-plan preview MPC on the delay-aware GP model (``preview-mpc``, the default controller of ``launch.py``).

Each update at state k (:meth:`PreviewMPC.update`):

1. **Estimate** (:class:`~controller_node.preview_stages.Estimator`): the output disturbance ``d̂``
   (offset-free control) is a random-walk observer on the model's one-step error,
   ``d̂ ← d̂ + L (x[k] − x̂[k|k−1] − d̂)``.
2. **Forecast**: T ahead over the horizon from the scan-plan preview carried by the state
   (``track_elapsed_s``, ``track_remaining_s``, ``next_track``) and the turnaround profile
   (:func:`gp_model.narx.forecast_t_ahead`, compiled); the profile of the last turnaround seen in this
   run replaces the trained one where it has been observed (learning from the run).
3. **Predict**: ``x̂[k+m] = c₀ + Σ b_i p[k+m−i] + Σ c_j T[k+m−1−j] + Σ g_l F[k+m−l] + r(ψ_{k+m−1}) + d̂``,
   m = 1..H (model of :mod:`gp_model.narx`), affine in the planned powers; the turnaround feature
   ``F`` (:mod:`gp_model.plan_feature`) after the turn ahead is linear in the planned powers
   before it, so the plan sees what power before a turn does after it.
4. **Optimise**: the QP of :mod:`controller_node.preview_qp` (tracking of the set point,
   move penalty, hard power bounds, soft area bounds tightened by the GP's predictive std).

Steps 1–4 are one compiled call, :func:`~controller_node.preview_kernel.control_step`, on the
stages' structures (:mod:`controller_node.preview_stages`), shared by the full update and both
phases of the real-time iteration; the state's place on the scan plan is its
:class:`~controller_node.preview_stages.StateContext`.

**Real-time iteration.** After the command is sent, :meth:`PreviewMPC.prepare` (the node calls
it) runs steps 2–4 for the state expected next (the next step of the same track, with the power
just commanded and the forecast T ahead) and keeps the linearisation, the QP's Hessian and its
factor, and moments of the GP's kernel sums. When that state arrives, :meth:`~PreviewMPC.update`
takes the feedback phase (:func:`~controller_node.preview_kernel.feedback_into`): steps 1–3 at
the measured T ahead and area, the GP's sums moved to it by a series (exact to ~1e-9), then step 4
on the prepared linearisation. Any other state (a gap, a new track or layer, another power, a T
ahead far from the forecast) gets the full update.

The pool build-up (the first ``observer_start_steps`` states of the run and of every layer of a
build) is outside the fitted model: there the observer stands still and the QP does not track the
states inside the build-up, only those after it (the powers of the build-up are lags of theirs).
Step 0 gets the nominal power, for every controller. A layer's first track is forecast as the
run's first (no turnaround).

Learning over turnarounds (iterative learning control on the model's one-step error after a
turn, :meth:`PreviewMPC._learn_turn_correction`): within a layer each turn starts from the latest
learned correction; in the next layer (of the same build, or through :meth:`learning_state`)
turn j starts from what turn j learned, since a later turn of a layer is on a hotter plate.

A state whose sample period or scan speed differs from the model's by more than 1 % is refused
(:class:`~controller_node.types.ConfigurationError` with the line of
:func:`~controller_node.process.process_mismatch`: the node logs it and ends with exit status 2);
``launch.py`` refuses them, and another material, before a run.
"""

from __future__ import annotations

import math

import numpy as np

from gp_model.compiled import compile_lock

from . import preview_kernel
from .base import Controller, Proposal
from .learning_state import LEARNING_FORMAT, parse_learning_state
from .preview_kernel import Kernel
from .preview_qp import PreviewQP
from .preview_stages import StateContext
from .process import PERIOD_TOLERANCE, SPEED_TOLERANCE, process_mismatch
from .settings import ControllerSettings
from .types import ConfigurationError, Measurement

__all__ = ["PreviewMPC"]

class PreviewMPC(Controller):
    """Preview MPC (module docstring).

    Parameters
    ----------
    settings : ControllerSettings
        ``settings.preview`` configures it.
    model : gp_model.narx.NarxGPModel
        Delay-aware model (FIR part, residual GP, turnaround profile, sample period).

    Attributes
    ----------
    n_feedback : int
        Updates of this run that took the feedback phase of a preparation (:meth:`prepare`).
    """

    name = "preview-mpc"
    feedback = True
    """Whether the observer runs on the measured area (:class:`~controller_node.scan_feedforward.ScanFeedForward`:
    never)."""

    def __init__(self, settings: ControllerSettings, model) -> None:
        self.model = model
        ps = settings.preview
        h, b = ps.horizon, model.power_coefficients
        self._nb, self._h = b.size, h
        self.qp = PreviewQP(h, settings.set_point_m2, q=ps.q, q_f=ps.q_f, r=ps.r, power_scale_w=ps.power_scale_w,
                            power_min_w=settings.power_min_w, power_max_w=settings.power_max_w,
                            area_min_m2=ps.area_min_m2, area_max_m2=ps.area_max_m2,
                            slack_linear=ps.slack_linear, slack_quadratic=ps.slack_quadratic)
        with compile_lock(preview_kernel.__file__):   # one process compiles on a fresh install, the others load
            self._kernel = Kernel(model, self.qp, h if ps.uncertainty_z > 0 else 1, ps.uncertainty_z,
                                  len(model.turn_profile_k), ps.turn_learning_steps, ps.observer_gain)
            self._warm_up()
        self._period_s, self._speed_m_s = model.sample_period_s, model.speed_m_s
        super().__init__(settings)              # reset(): the run's state, after the warm-up wrote into it

    def _warm_up(self) -> None:
        """Call the compiled update, preparation and feedback once, with the argument types of a run,
        pushing nothing into the histories, and the accessors of the paths where a bound is active or
        the solver fails: they are compiled (or loaded from numba's cache) now, not at the first states
        of a run that take them."""
        k, context = self._kernel, StateContext(0, 0.0, 0, True, 0, True, -1, False, 0.0, True, self._h)
        k.update(context, 0.0, 0.0)
        k.prepare(context, 0.0)
        k.prepared = True                        # the feedback is compiled whatever this preparation gave
        k.feedback(context, 0.0, 0.0)
        _ = k.has_step
        k.estimator.forget_prediction()

    def reset(self) -> None:
        """Forget the run: histories, disturbance estimate, plan, learned turnaround profile."""
        super().reset()
        k = self._kernel
        self._p, self._t = k.p_hist, k.t_hist     # p[k], p[k−1], ... and T[k−n_T+1 .. k], in the kernel
        self._p[:] = 0.0
        self._t_known = False                    # T history filled with the first state's
        self.path_lengths_m: list[float] = []   # the paths of the current layer's plan, as the states show them
        self._p_fill = self._t_fill = 0          # copies of p[k], T[k] that the next update pushes
        self._prev: Measurement | None = None
        self._first: Measurement | None = None
        self._first_track: int | None = None
        self._track_start_step = 0
        self._layer_start_step = 0               # laser-on of the current layer (a new pool)
        self._turn_base_k: float | None = None   # T ahead in the state before the last turn
        self._observed: list[float] = []        # T rise after the last turn, as seen
        self._profile = k.profile
        self._profile[:] = self.model.turn_profile_k
        self._plan = k.plan
        self._plan[:] = self.settings.nominal_power_w
        k.p_long[:], k.f_hist[:] = 0.0, 0.0              # the turnaround feature's histories
        k.start_track(False)
        k.estimator.reset()                      # d̂ = 0, no x̂[k+1|k] yet, no error seen after a turn
        n = self.settings.preview.turn_learning_steps
        self.turn_correction_m2 = np.zeros(n)    # learned model error after a turnaround, by state since the turn
        self._turn = -1                          # index of the current turn in the layer (-1: first track)
        self.turn_corrections_by_turn_m2: list[np.ndarray] = []   # learned for turn j of this layer
        self._prior_by_turn: list[np.ndarray] = []                # learned for turn j of the previous layer
        self._learned = False
        self._sync_corrections()
        self._last_qp: int | None = None        # blind rows of the QP in the workspace (see last_qp)
        self._last_context: StateContext | None = None   # of the last update, if it may be prepared after
        self._prepared_for: StateContext | None = None   # the state the kernel is prepared for
        self.n_feedback = 0                      # updates that took the feedback phase (prepare)
        k.prepared = False

    # ------------------------------------------------------------------ bookkeeping
    def _check_process(self, m: Measurement) -> None:
        """Refuse a state at another speed, or at another sample period since the run's first state
        (:class:`~controller_node.types.ConfigurationError` naming both)."""
        first = self._first
        steps = m.step - first.step
        reason = None
        if not abs(m.speed_m_s / self._speed_m_s - 1.0) <= SPEED_TOLERANCE:
            reason = process_mismatch(self.model, speed_m_s=m.speed_m_s)
        elif steps and not abs((m.time_s - first.time_s) / (steps * self._period_s) - 1.0) <= PERIOD_TOLERANCE:
            reason = process_mismatch(self.model, sample_period_s=(m.time_s - first.time_s) / steps)
        if reason is not None:
            raise ConfigurationError(reason)

    def _observe(self, m: Measurement, prev: Measurement | None, next_on_track: bool) -> None:
        """Count the copies of ``p[k]``, ``T[k]`` the update pushes into the histories (one per step
        since the last state) and follow tracks and turnarounds (``next_on_track``: ``m`` is the next
        step of ``prev``'s track and layer)."""
        if next_on_track:                        # one copy of each
            self._p_fill = self._t_fill = 1
        else:
            self._observe_jump(m, prev)
        if m.track_elapsed_s is not None:
            self._track_start_step = m.step - round(m.track_elapsed_s / self._period_s)
        if not next_on_track and m.track_remaining_s is not None and m.track_elapsed_s is not None \
                and m.track_elapsed_s <= 1.5 * self._period_s \
                and (prev is None or m.track != prev.track or m.layer != prev.layer):   # the first state of a path
            self.path_lengths_m.append((m.track_elapsed_s + m.track_remaining_s) * m.speed_m_s)
        if self._turn_base_k is not None:
            self._observed.append(m.t_ahead_k - self._turn_base_k)

    def _observe_jump(self, m: Measurement, prev: Measurement | None) -> None:
        """:meth:`_observe` for a first state, a gap in the steps, a new track or a new layer."""
        gap = 1 if prev is None else max(1, m.step - prev.step)
        self._p_fill = min(gap, self._nb)
        if m.step == 0:
            self._p[:] = 0.0
            self._p_fill = 0
        self._t_fill = min(gap, self._t.size)
        if not self._t_known:
            self._t[:] = m.t_ahead_k
            self._t_known, self._t_fill = True, 0
        if self._first_track is None:
            self._first_track = m.track
        new_layer = prev is not None and m.layer is not None and m.layer != prev.layer
        if new_layer:  # a new pool on fresh powder: no turnaround to learn from or forecast
            self._layer_start_step = self._track_start_step = m.step
            self.path_lengths_m = []
            self._first_track, self._turn_base_k, self._observed = m.track, None, []
            self._kernel.start_track(False)
            self._learn_turn_correction()
            self._prior_by_turn, self.turn_corrections_by_turn_m2 = self.turn_corrections_by_turn_m2, []
            self._turn = -1
            self._sync_corrections()
        new_track = not new_layer and prev is not None and m.track is not None and m.track != prev.track
        if new_track:
            self._learn_profile()
            self._learn_turn_correction()
            self._turn += 1
            self._turn_base_k = prev.t_ahead_k
            self._kernel.start_track(True)
            self._observed = []
            self._track_start_step = m.step
            self._sync_corrections()

    def _correction_for(self, turn: int) -> np.ndarray:
        """The correction applied after turn ``turn`` of the layer: what the previous layer learned at
        the same turn, else the latest learned in this run."""
        return self._prior_by_turn[turn] if 0 <= turn < len(self._prior_by_turn) else self.turn_correction_m2

    def _sync_corrections(self) -> None:
        """Copy the corrections after the current track's turn and after the next turn into the kernel
        (after every change of the turn index or of what was learned)."""
        self._kernel.current[:] = self._correction_for(self._turn)
        self._kernel.following[:] = self._correction_for(self._turn + 1)
        self._prepared_for = None

    def _learn_turn_correction(self) -> None:
        """Iterative learning over turnarounds: ``c ← (1 − γ)(c_j + κ ε_j)`` with ``c_j`` the correction
        applied after turn j, ``ε_j`` the one-step errors seen after it (where seen) and γ the forgetting
        (``turn_learning_forgetting``). ``c`` is applied after the next turns of this layer; ``c_j`` after
        turn j of the next layer (its own turn: a later turn of a layer is on a hotter plate)."""
        k, ps = self._kernel, self.settings.preview
        if self._turn >= 0:
            seen = k.turn_error_seen
            learned = self._correction_for(self._turn).copy()
            learned[seen] += ps.turn_learning_gain * k.turn_errors[seen]
            learned *= 1.0 - ps.turn_learning_forgetting
            self.turn_correction_m2 = learned
            self.turn_corrections_by_turn_m2.append(learned)
            self._learned = self._learned or bool(np.any(learned))
        k.turn_error_seen[:] = False

    def finish_run(self) -> None:
        """Fold the errors after the last turn of the run into the learned correction."""
        self._learn_turn_correction()

    def learning_state(self) -> dict:
        """What the controller learned in this run (turnaround correction and T-rise profile) and the
        paths of the last layer's plan it learned on, JSON-able, to start the next layer with
        (:meth:`load_learning_state`; ``launch.py`` refuses it for a run on another plan)."""
        return {"format": LEARNING_FORMAT, "sample_period_s": self.model.sample_period_s,
                "turn_correction_m2": self.turn_correction_m2.tolist(),
                "turn_corrections_by_turn_m2": [c.tolist() for c in self.turn_corrections_by_turn_m2],
                "turn_profile_k": self._profile.tolist(), "path_lengths_m": list(self.path_lengths_m)}

    def load_learning_state(self, doc: object) -> None:
        """Start from a previous run's :meth:`learning_state` (``ValueError`` with one line if it does not fit)."""
        correction, by_turn, profile = parse_learning_state(doc, self.model.sample_period_s,
                                                            self.turn_correction_m2.size, self._profile.size)
        self.turn_correction_m2[:] = correction
        self._prior_by_turn = by_turn
        self._profile[:] = profile
        self._learned = bool(np.any(correction)) or any(bool(np.any(c)) for c in by_turn)
        self._sync_corrections()

    def _learn_profile(self) -> None:
        """Replace the trained turnaround profile by the one just observed, where observed."""
        if self.settings.preview.learn_turn_profile and self._observed:
            n = min(len(self._observed), self._profile.size)
            self._profile[:n] = self._observed[:n]
            self._profile[n:] = self._profile[n - 1] if n < self._profile.size and n > 0 else self._profile[n:]
            self._prepared_for = None

    # ------------------------------------------------------------------ control law
    def prepare(self) -> None:
        """Preparation phase of a real-time iteration, to run after the command is sent and before the
        next state arrives: linearise and factor the QP of the state expected next (the next step of
        the same track, with the power just commanded and the forecast T ahead), so that its
        :meth:`update` only moves the prediction by the measured T ahead and area and solves
        (:func:`~controller_node.preview_kernel.feedback_into`). Any other next state (a gap, a new
        track or layer, another power) gets the full update, as without a preparation. Nothing is
        prepared after a state that did not follow the previous one by one step: a loop that skips
        states would not use the preparation."""
        last = self._last_context
        if last is None or last.to_end == 0:    # the next state starts a track
            return
        ps, step = self.settings.preview, self._prev.step + 1
        built_up = step - self._layer_start_step >= ps.observer_start_steps
        nxt = StateContext(1, self._fallback.last_power_w, 1, built_up and self.feedback, last.since + 1, last.on_first,
                           max(last.to_end - 1, -1), last.has_turn_base, last.turn_base_k, last.learned,
                           0 if built_up else ps.observer_start_steps - (step - self._layer_start_step) - 1)
        if self._kernel.prepare(nxt, float(self._kernel.forecast[0])):
            self._prepared_for = nxt

    @property
    def last_qp(self) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None] | None:
        """The QP of the last update (benchmarks, tests): copies of Γ (H, H) and c (H,), ``p[k]`` [W]
        and the bound tightening (None without); None if the last update solved no QP."""
        if self._last_qp is None:
            return None
        return (*self._tracked(self._last_qp), float(self._p[0]), self._margin())

    @property
    def disturbance_m2(self) -> float:
        """The observer's output disturbance estimate d̂ [m²]."""
        return self._kernel.estimator.disturbance_m2

    def _tracked(self, blind: int) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the workspace's Γ, c with the ``blind`` leading rows (not tracked) zero."""
        gamma, c = self._kernel.gamma.copy(), self._kernel.c.copy()
        gamma[:blind], c[:blind] = 0.0, 0.0
        return gamma, c

    def _margin(self) -> np.ndarray | None:
        """The area bounds' tightening zσ / x_sp of the workspace's rows (None without)."""
        z_sigma = self.settings.preview.uncertainty_z
        return z_sigma * self._kernel.std / self.settings.set_point_m2 if z_sigma > 0 else None

    def _propose(self, m: Measurement) -> Proposal:
        ps = self.settings.preview
        prev = self._prev
        if self._first is None:
            self._first = m
        self._check_process(m)
        consecutive = prev is not None and m.step == prev.step + 1
        self._observe(m, prev, consecutive and m.track == prev.track and m.layer == prev.layer and self._t_known)
        built_up = m.step - self._layer_start_step >= ps.observer_start_steps
        self._prev = m
        since = m.step - self._track_start_step
        to_end = -1                              # no turn ahead
        if m.track_remaining_s is not None and m.next_track is not False:  # (False: the layer ends here)
            to_end = max(round(m.track_remaining_s / self._period_s) - 1, 0)
        on_first = m.track is None or m.track == self._first_track
        blind = 0 if built_up else ps.observer_start_steps - (m.step - self._layer_start_step) - 1
        self._last_qp = None                     # the workspace is overwritten now
        work = self._kernel
        has_base = self._turn_base_k is not None
        context = tuple.__new__(StateContext, (   # (not the class's constructor: a Python call on this path)
            self._p_fill, m.power_w, self._t_fill, consecutive and built_up and self.feedback, since, on_first,
            to_end, has_base, self._turn_base_k if has_base else 0.0, self._learned, blind))
        # estimate, predict, plan in one compiled call (preview_kernel.control_step); the feedback
        # phase of the real-time iteration when this is the state prepared for, else the full update
        status = -1
        if work.prepared and context == self._prepared_for:
            status = work.feedback(context, m.t_ahead_k, m.area_m2)
        if status >= 0:
            self.n_feedback += 1
        else:
            status = work.update(context, m.t_ahead_k, m.area_m2)
        self._prepared_for = None
        # prepare only while states come one step apart: a loop that skips states (a free-running
        # sensor faster than the controller) would not use the preparation and pays for it in CPU
        self._last_context = context if status != 2 and consecutive else None
        if status == 2:  # an absurd input: no plan from it
            return Proposal(math.nan, status="model_error")
        self._last_qp = blind
        areas, fast = work.areas, status == 0
        if not fast:     # apply: a bound is active, the kernel's step is not the solution (the plan is unchanged)
            gamma, c = self._tracked(blind)
            result = self.qp.finish(gamma, c, work.hess, work.f, work.v if work.has_step else None, self._margin())
            if result.path.startswith("failed"):
                work.estimator.forget_prediction()  # no prediction from this state
                return Proposal(math.nan, status=f"solver_{result.path}")
            plan = np.concatenate((self._plan[1:], self._plan[-1:]))   # ū = p̄[k+1..k+H]
            new_plan, fast = result.power_w, result.path == "fast"
            sp = self.settings.set_point_m2
            areas = work.predicted + (work.gamma * (sp / self.qp.scale)) @ (new_plan - plan)  # ∂x̂/∂u times the move
            self._plan[:] = new_plan
        plan_w = tuple(self._plan.tolist())
        return Proposal(plan_w[0], "ok", tuple(areas.tolist()), plan_w, float(work.std[0]),
                        solver_iterations=0 if fast else 1)
