"""Top-surface temperature as a colour-mapped ``foxglove.RawImage`` (rgb8)."""

from __future__ import annotations

import numpy as np

from messages import RawImage, Timestamp

# "inferno"-like anchors (value in [0, 1] → RGB), enough for a readable heat map.
_ANCHORS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
_COLOURS = np.array([[0, 0, 4], [87, 16, 110], [188, 55, 84], [249, 142, 9], [252, 255, 164]], dtype=float)


def colour_map(temperature_k: np.ndarray, t_min_k: float, t_max_k: float) -> np.ndarray:
    """Map temperatures to RGB bytes, shape ``temperature_k.shape + (3,)`` (uint8)."""
    v = np.clip((temperature_k - t_min_k) / (t_max_k - t_min_k), 0.0, 1.0)
    rgb = np.stack([np.interp(v, _ANCHORS, _COLOURS[:, c]) for c in range(3)], axis=-1)
    return rgb.round().astype(np.uint8)


def temperature_image(image_k: np.ndarray, time_s: float, t_min_k: float, t_max_k: float) -> RawImage:
    """``foxglove.RawImage`` of a temperature raster (rows = +y upwards in the picture)."""
    rgb = colour_map(image_k[::-1], t_min_k, t_max_k)
    height, width, _ = rgb.shape
    return RawImage(
        timestamp=Timestamp.from_seconds(time_s), frame_id="top_surface", width=width, height=height,
        encoding="rgb8", step=3 * width, data=rgb.tobytes(),
    )
