"""What a camera at frame period P sees of the FE plant, which steps at Δt = ``dt_s``.

A coaxial camera and its laser driver run at one frame period P = k Δt (k a whole number): the
driver holds the commanded power over a frame (zero-order hold) and the camera delivers one state
per frame. Of the FE run's states (one per Δt) the camera sees every k-th, state j k, as its frame
j at time j P; the power it reports for frame j is the one held over the k steps that led to it.
The FE node with ``[plant] frame_period_s`` publishes these frames (:func:`camera_frame` after every
k steps under one command); :func:`camera_frames` is the same view of a whole recorded run.
Everything is SI.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TypeVar

import msgspec

__all__ = ["camera_frame", "camera_frames", "frame_ratio"]

RATIO_TOLERANCE = 1e-6
"""Relative difference between the frame period and a whole number of FE steps that is accepted."""

State = TypeVar("State")


def frame_ratio(frame_period_s: float, dt_s: float, name: str = "--frame-period-s") -> int:
    """k = ``frame_period_s`` / ``dt_s`` [-], FE steps per frame.

    Raises
    ------
    ValueError
        One line naming ``name``: the frame period is not a whole number (>= 1) of FE steps.
    """
    ratio = frame_period_s / dt_s if dt_s > 0 else float("nan")
    k = round(ratio) if ratio == ratio and ratio < 1e9 else 0
    if not (k >= 1 and abs(ratio - k) <= RATIO_TOLERANCE * ratio):
        raise ValueError(f"{name} must be a whole number of FE steps of {dt_s * 1e6:g} µs, "
                         f"got {frame_period_s:g} s ({ratio:.4g} steps)")
    return k


def camera_frame(steps: Sequence[State], frame: int, frame_period_s: float) -> State:
    """Frame ``frame`` of a camera at ``frame_period_s`` [s]: the last of ``steps``, the FE states of
    the frame's k steps (dataclasses or messages, each with the ``power_w`` [W] applied during its
    step), as step ``frame`` at time ``frame * frame_period_s`` [s].

    Raises
    ------
    ValueError
        No states, or a power that was not held over the frame.
    """
    if not steps:
        raise ValueError(f"frame {frame}: no FE steps")
    powers = {s.power_w for s in steps}
    if len(powers) > 1:
        raise ValueError(f"frame {frame}: the power is not held over the frame ({min(powers):g}-{max(powers):g} W); "
                         "a camera-rate run holds each command for a whole frame")
    last = steps[-1]
    replace = msgspec.structs.replace if isinstance(last, msgspec.Struct) else dataclasses.replace
    return replace(last, step=frame, time_s=frame * frame_period_s)


def camera_frames(states: Sequence[State], steps_per_frame: int, frame_period_s: float) -> list[State]:
    """The frames a camera at ``frame_period_s`` [s] sees of an FE run's states (step 0, 1, 2, ...,
    as :func:`camera_frame` takes them): state 0, then :func:`camera_frame` of
    every whole frame of ``steps_per_frame`` steps (a last partial frame is not seen).

    Raises
    ------
    ValueError
        ``steps_per_frame`` < 1, or a power not held over a frame.
    """
    k = steps_per_frame
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"steps_per_frame must be an int >= 1, got {k!r}")
    if not states:
        return []
    frames = range(1, (len(states) - 1) // k + 1)
    return [camera_frame(states[:1], 0, frame_period_s)] + [
        camera_frame(states[(j - 1) * k + 1:j * k + 1], j, frame_period_s) for j in frames]
