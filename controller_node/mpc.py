"""GP-MPC of eq. (7)-(8): linearise the GP mean each step, solve the tracking QP.

:class:`MPCController` wraps linearisation (:func:`controller_node.model.linearise`),
normalisation (:func:`controller_node.qp.build_qp_data`), one of three backends of
the same QP — ``"daqp"`` (condensed, exact, fastest; default), ``"osqp"`` (sparse,
warm-started), ``"cvxpy"`` (readable reference) — the optional output-disturbance
estimate and the optional temperature feed-forward.
"""

from __future__ import annotations

import math

from .base import Controller, Proposal
from .feedforward import temperature_feedforward_w
from .model import DynamicsModel, Linearisation, guard, linearise, operating_point
from .qp import _MAX_STATE_GAIN, QPBackend, build_qp_data, power_scale_w
from .settings import ControllerSettings
from .types import Measurement

__all__ = ["MPCController", "make_backend"]


def make_backend(settings: ControllerSettings) -> QPBackend:
    """Build the QP backend named by ``settings.mpc.solver``.

    Parameters
    ----------
    settings : ControllerSettings
        Controller settings.

    Returns
    -------
    QPBackend
        :class:`~controller_node.qp_daqp.DaqpBackend`,
        :class:`~controller_node.qp_osqp.OSQPBackend` or
        :class:`~controller_node.mpc_reference.CvxpyBackend`.
    """
    solver = settings.mpc.solver
    if solver == "daqp":
        from .qp_daqp import DaqpBackend

        return DaqpBackend(settings)
    if solver == "osqp":
        from .qp_osqp import OSQPBackend

        return OSQPBackend(settings)
    from .mpc_reference import CvxpyBackend

    return CvxpyBackend(settings)


class MPCController(Controller):
    """Linear time-varying GP-MPC (paper eq. 7-8) with soft area bounds.

    Each update linearises the model mean at ``z0 = (x[k], T[k], p[k−1], v[, x[k] − x[k−1]])``
    with the affine term (a history model gets the previous sample's area when it is step
    ``k−1`` of the same track, else no change), builds the normalised QP (:func:`controller_node.qp.build_qp_data`),
    solves it, applies the first planned power plus the optional temperature
    feed-forward and keeps the plan for the fallback.

    Parameters
    ----------
    settings : ControllerSettings
        ``settings.mpc`` configures the MPC.
    model : DynamicsModel
        One-step model with ``predict`` and ``mean_and_jacobian``.
    backend : QPBackend, optional
        QP solver; default :func:`make_backend` (``settings.mpc.solver``).
    """

    name = "mpc"

    def __init__(self, settings: ControllerSettings, model: DynamicsModel, backend: QPBackend | None = None) -> None:
        if not isinstance(model, DynamicsModel):
            raise ValueError("model must provide predict(z) and mean_and_jacobian(z)")
        super().__init__(settings)
        self.model = model
        self.backend = make_backend(settings) if backend is None else backend

    def reset(self) -> None:
        """Forget history, including the disturbance estimate and the last linearisation."""
        super().reset()
        self._previous: tuple[Measurement, Linearisation] | None = None
        self._feedforward_w = 0.0  # feed-forward included in the last command
        self.disturbance_m2 = 0.0

    def _propose(self, m: Measurement) -> Proposal:
        s = self.settings
        mpc = s.mpc
        ff = mpc.feedforward
        previous = self._previous if self._previous is not None and self._previous[0].step == m.step - 1 else None
        same_track = previous is not None and (m.track is None or previous[0].track in (None, m.track))
        x_prev = previous[0].area_m2 if same_track else None
        # the power the MPC planned for the step just applied: applied minus its feed-forward
        applied = min(max(m.power_w, s.power_min_w), s.power_max_w)
        planned_prev = applied - (self._feedforward_w if previous is not None else 0.0)
        feedforward = 0.0
        t_lin = m.t_ahead_k
        raw = None
        if ff.enabled:
            t_prev = previous[0].t_ahead_k if previous is not None else m.t_ahead_k
            gain = ff.gain_w_per_k
            if gain is None:
                raw = linearise(self.model, operating_point(
                    self.model, m.area_m2, m.t_ahead_k, min(max(planned_prev, s.power_min_w), s.power_max_w),
                    m.speed_m_s, x_prev), mpc.report_model_std)
                if raw is None:
                    return Proposal(math.nan, status="model_error")
                gain = raw.temperature_gain_w_per_k()
            feedforward = temperature_feedforward_w(ff, gain, m.t_ahead_k, t_prev)
            # with the direct term the plant seen by the MPC behaves as at T_ref (to first order)
            t_lin = m.t_ahead_k - ff.direct_gain * (m.t_ahead_k - ff.reference_temperature_k)
        p0 = min(max(planned_prev, s.power_min_w), s.power_max_w)
        z0 = operating_point(self.model, m.area_m2, t_lin, p0, m.speed_m_s, x_prev)
        lin = raw if raw is not None and t_lin == m.t_ahead_k else linearise(self.model, z0, mpc.report_model_std)
        if lin is None or not lin.spectral_radius() <= _MAX_STATE_GAIN:
            return Proposal(math.nan, status="model_error")
        lin = guard(lin, mpc.state_gain_max, mpc.power_gain_min_m2_per_w)
        if previous is not None and mpc.disturbance_gain > 0.0:
            prev_lin = previous[1]
            predicted = prev_lin.f0 + prev_lin.b * (planned_prev - prev_lin.z0[2])
            self.disturbance_m2 += mpc.disturbance_gain * (m.area_m2 - predicted - self.disturbance_m2)
        if previous is not None and mpc.integral_gain > 0.0:
            error = m.area_m2 - s.set_point_m2
            # conditional integration: no wind-up at hot track starts
            if abs(error) <= mpc.integral_band * s.set_point_m2:
                self.disturbance_m2 += mpc.integral_gain * (1.0 - lin.a - lin.a_prev) * error
        self._previous = (m, lin)

        data = build_qp_data(lin, m.area_m2, planned_prev, self.disturbance_m2, s, feedforward)
        if data is None:
            return Proposal(math.nan, status="model_error")
        sol = self.backend.solve(data)
        if sol.status != "solved":
            return Proposal(math.nan, status=f"solver_failed:{sol.status}")

        self._feedforward_w = feedforward
        plan = data.p_ref_w + power_scale_w(s) * sol.u + feedforward
        areas = s.set_point_m2 * (1.0 + sol.e)
        var = lin.variance_m4
        std = math.sqrt(var) if var is not None and math.isfinite(var) and var >= 0.0 else None
        return Proposal(
            power_w=float(plan[0]),
            predicted_power_w=tuple(plan.tolist()),
            predicted_area_m2=tuple(areas.tolist()),
            model_std_m2=std,
            feedforward_w=feedforward,
            reference_power_w=data.p_ref_w + feedforward,
            solver_iterations=sol.iterations,
        )
