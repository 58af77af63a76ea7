"""One valid example of every contract message type (used by several tests)."""

from __future__ import annotations

from messages import (
    ControllerDiagnostics,
    LaserCommand,
    Log,
    LogLevel,
    MeltPoolState,
    PlantDiagnostics,
    RawImage,
    RunEvent,
    Timestamp,
)
from messages.topics import (
    CONTROLLER_DIAGNOSTICS,
    LASER_COMMAND,
    LOG,
    PLANT_DIAGNOSTICS,
    PLANT_STATE,
    PLANT_TEMPERATURE,
    RUN_EVENTS,
)


def sample_messages(run_id: str, step: int = 3):
    """``[(topic, message), ...]`` covering every registered topic."""
    t = step * 50e-6
    return [
        (
            PLANT_STATE,
            MeltPoolState(
                run_id=run_id,
                step=step,
                time_s=t,
                laser_x_mm=1.25,
                laser_y_mm=-0.1,
                scan_dir_x=-1.0,
                scan_dir_y=0.0,
                track=1,
                area_mm2=0.0712,
                t_ahead_k=612.5,
                power_w=250.0,
                speed_mm_s=800.0,
                width_um=131.0,
                length_um=402.0,
                depth_um=None,
                cross_section_mm2=0.0061,
                t_peak_k=2890.0,
            ),
        ),
        (
            LASER_COMMAND,
            LaserCommand(run_id=run_id, step=step + 1, time_s=t, power_w=243.5, speed_mm_s=800.0, controller="mpc"),
        ),
        (
            CONTROLLER_DIAGNOSTICS,
            ControllerDiagnostics(
                run_id=run_id,
                step=step + 1,
                time_s=t,
                controller="mpc",
                status="solved",
                solve_time_us=57.3,
                setpoint_mm2=0.07,
                predicted_area_mm2=[0.071, 0.0705],
                predicted_power_w=[243.5, 244.0],
                model_std_mm2=0.0008,
            ),
        ),
        (
            PLANT_DIAGNOSTICS,
            PlantDiagnostics(
                run_id=run_id,
                step=step,
                time_s=t,
                step_wall_ms=14.2,
                absorbed_j=0.015,
                stored_j=0.0149,
                lost_j=1e-5,
                energy_error_pct=1e-6,
            ),
        ),
        (
            PLANT_TEMPERATURE,
            RawImage(
                timestamp=Timestamp.from_seconds(t),
                frame_id="top_surface",
                width=3,
                height=2,
                encoding="rgb8",
                step=9,
                data=bytes(range(18)),
            ),
        ),
        (
            RUN_EVENTS,
            RunEvent(
                run_id=run_id, node="fe_node", event="start", time_s=0.0, config_json='{"h_um": 25}', total_steps=1000
            ),
        ),
        (
            LOG,
            Log(
                timestamp=Timestamp.from_seconds(t),
                level=LogLevel.WARNING,
                message="command timeout; holding 250 W",
                name="fe_node",
            ),
        ),
    ]
