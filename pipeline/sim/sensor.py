"""From a rendered frame to what a depth camera publishes: object labels, noise, a labelled cloud."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.sim.noise import NO_LABEL, DepthNoiseConfig, apply_depth_noise
from robonav.pipeline.sim.rendering import DepthFrame


@dataclass(frozen=True)
class SensorFrame:
    """One camera frame as published: depth, per-pixel labels and the camera model."""

    depth_m: npt.NDArray[np.float32]
    """(H, W) depth along the optical axis [m]; +inf where there is no return."""
    labels: npt.NDArray[np.int32]
    """(H, W) object label per pixel; `NO_LABEL` (-1) for no return or no object."""
    intrinsics: CameraIntrinsics


def label_image(segmentation: npt.NDArray[np.integer], label_of_body: Mapping[int, int]) -> npt.NDArray[np.int32]:
    """Map per-pixel pybullet body ids to labels.

    Args:
        segmentation: (H, W) body unique ids, -1 for background.
        label_of_body: Body unique id -> label (>= 0); bodies not listed get `NO_LABEL`.

    Returns:
        (H, W) int32 labels.
    """
    seg = np.asarray(segmentation)
    size = max([int(seg.max(initial=-1)) + 1, *(b + 1 for b in label_of_body)])
    lookup = np.full(size + 1, NO_LABEL, dtype=np.int32)  # the last slot serves id -1
    for body, label in label_of_body.items():
        if body >= 0:
            lookup[body] = label
    return lookup[np.where(seg < 0, size, seg)]


def sensor_frame(frame: DepthFrame, label_of_body: Mapping[int, int], noise: DepthNoiseConfig,
                 rng: np.random.Generator) -> SensorFrame:
    """Label a rendered frame and corrupt it with `noise`."""
    depth, labels = apply_depth_noise(frame.depth_m, label_image(frame.segmentation, label_of_body),
                                      frame.intrinsics, noise, rng)
    return SensorFrame(depth, labels, frame.intrinsics)


def labelled_cloud(frame: SensorFrame, *, max_depth_m: float) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Back-project a frame to points in the optical frame, each with its pixel's label.

    Returns:
        (N, 3) float32 points [m] in row-major pixel order and (N,) int32 labels; pixels with
        no return or at or beyond `max_depth_m` give no point.
    """
    points = points_from_depth(frame.depth_m, frame.intrinsics, max_depth_m=max_depth_m)
    z = frame.depth_m.ravel()
    # The same pixels points_from_depth keeps (finite, 0 < z < max), in the same order.
    kept = np.isfinite(z) & (z > 0) & (z < max_depth_m)
    labels = frame.labels.ravel()[kept]
    if labels.shape[0] != points.shape[0]:
        raise AssertionError(f"label count {labels.shape[0]} != point count {points.shape[0]}")
    return points, labels
