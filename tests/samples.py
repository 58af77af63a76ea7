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
from messages.foxglove import (
    IDENTITY,
    Color,
    LinePrimitive,
    LineType,
    ModelPrimitive,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    Vector3,
)
from messages.topics import (
    CONTROLLER_DIAGNOSTICS,
    LASER_COMMAND,
    LOG,
    PLANT_DIAGNOSTICS,
    PLANT_LASER,
    PLANT_SCENE,
    PLANT_STATE,
    PLANT_TEMPERATURE,
    RUN_EVENTS,
)

ORIGIN = Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=IDENTITY)


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
            PLANT_LASER,
            PoseInFrame(timestamp=Timestamp.from_seconds(t), frame_id="plate", pose=Pose(
                position=Vector3(x=-5e-3, y=1e-4, z=5e-5), orientation=Quaternion.about_z(3.141592653589793))),
        ),
        (
            PLANT_SCENE,
            SceneUpdate(entities=[
                SceneEntity(timestamp=Timestamp.from_seconds(t), frame_id="plate", id="scan_plan", lines=[LinePrimitive(
                    type=LineType.LINE_LIST, pose=ORIGIN, thickness=2.0, scale_invariant=True,
                    points=[Vector3(x=-5e-3, y=0.0, z=0.0), Vector3(x=5e-3, y=0.0, z=0.0)],
                    color=Color(r=0.2, g=0.6, b=1.0, a=1.0))]),
                SceneEntity(timestamp=Timestamp.from_seconds(t), frame_id="plate", id="part", models=[ModelPrimitive(
                    pose=ORIGIN, scale=Vector3(x=1e-3, y=1e-3, z=1e-3), color=Color(r=0.7, g=0.7, b=0.7, a=0.4),
                    override_color=True, media_type="model/stl", data=b"solid x\nendsolid x\n")]),
            ]),
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
