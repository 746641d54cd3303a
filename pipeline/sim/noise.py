"""A depth-camera noise model: axial noise growing with distance, dropout, flying pixels, quantization.

Applied to a rendered depth image before it becomes a cloud, so every consumer (clouds,
depth images) sees the same corrupted frame. Each piece is switched off by a zero parameter;
`enabled: false` turns the whole model off. Randomness comes from the generator the caller
passes in (the sim seeds it per camera and frame from `seed`).

The shapes follow the usual structured-light / active-stereo error model: axial standard
deviation a + b z^2 (Khoshelham & Elberink 2012 for the Kinect; the same z^2 law follows
from disparity noise in stereo), disparity quantization z^2 * step / (f * baseline),
random dropout, and "flying" pixels that land between a foreground edge and the background
behind it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.config import require

NO_LABEL = -1
"""Label of pixels that show no object: background, dropout, flying pixels."""


@dataclass(frozen=True)
class DepthNoiseConfig:
    """Noise of one simulated depth camera; every piece is off when its parameter is 0."""

    enabled: bool = False
    """Master switch; false publishes the rendered depth exactly."""
    seed: int = 0
    """Seeds the noise; with the camera and the frame number it fixes every frame's noise."""
    axial_sigma_m: float = 0.001
    """Constant part of the axial (depth) standard deviation [m]."""
    axial_sigma_per_m2: float = 0.002
    """Distance-squared part: sigma(z) = axial_sigma_m + axial_sigma_per_m2 * z^2 [1/m]."""
    dropout_probability: float = 0.01
    """Chance that a pixel returns nothing, independently per pixel."""
    flying_pixel_probability: float = 0.3
    """Chance that a pixel at a depth edge (see `edge_threshold_m`) lands between the two surfaces."""
    edge_threshold_m: float = 0.05
    """A pixel is at an edge when a 4-neighbour's depth differs by more than this [m]."""
    quantization_step_m: float = 0.0
    """Depth rounded to multiples of this (e.g. 0.001 for a uint16 millimetre stream) [m]."""
    disparity_step_px: float = 0.0
    """Stereo disparity rounded to multiples of this (e.g. 1/16 px): a step in depth of
    z^2 * step / (fx * stereo_baseline_m) that grows with distance [px]."""
    stereo_baseline_m: float = 0.05
    """Baseline of the stereo pair, for `disparity_step_px` [m]."""
    latency_s: float = 0.0
    """Frames are published this long after the moment they show (the stamp stays that moment) [s]."""
    latency_jitter_s: float = 0.0
    """Uniform extra latency in [0, latency_jitter_s] per frame [s]."""

    def __post_init__(self) -> None:
        for key in ("axial_sigma_m", "axial_sigma_per_m2", "edge_threshold_m", "quantization_step_m",
                    "disparity_step_px", "latency_s", "latency_jitter_s"):
            value = getattr(self, key)
            require(math.isfinite(value) and value >= 0, f"noise.{key} must be a finite value >= 0, got {value}")
        for key in ("dropout_probability", "flying_pixel_probability"):
            value = getattr(self, key)
            require(0.0 <= value <= 1.0, f"noise.{key} must be in [0, 1], got {value}")
        require(self.stereo_baseline_m > 0, f"noise.stereo_baseline_m must be > 0, got {self.stereo_baseline_m}")

    def frame_rng(self, camera_index: int, frame: int) -> np.random.Generator:
        """The generator for one frame of one camera: reproducible from `seed` alone."""
        return np.random.default_rng((self.seed, camera_index, frame))


def apply_depth_noise(
    depth_m: npt.NDArray[np.floating],
    labels: npt.NDArray[np.int32],
    intrinsics: CameraIntrinsics,
    config: DepthNoiseConfig,
    rng: np.random.Generator,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Corrupt a depth image as `config` says.

    Args:
        depth_m: (H, W) depth along the optical axis [m]; inf/NaN/<= 0 means no return.
        labels: (H, W) per-pixel object labels; `NO_LABEL` where there is none.
        intrinsics: Camera model of the image (fx for disparity quantization).
        config: The noise model; with `enabled` false the inputs come back as copies.
        rng: Source of randomness.

    Returns:
        The noisy depth (H, W) float32 [m] (+inf for no return) and the labels (H, W) int32,
        set to `NO_LABEL` where a pixel dropped out or became a flying pixel.

    Raises:
        ValueError: the image and label shapes differ.
    """
    depth = np.array(depth_m, dtype=np.float32)
    out_labels = np.array(labels, dtype=np.int32)
    if depth.shape != out_labels.shape or depth.ndim != 2:
        raise ValueError(f"depth_m {depth.shape} and labels {out_labels.shape} must be the same (H, W) shape")
    depth[~(np.isfinite(depth) & (depth > 0))] = np.inf
    if not config.enabled:
        return depth, out_labels
    valid = np.isfinite(depth)
    if config.flying_pixel_probability > 0:
        _flying_pixels(depth, out_labels, config, rng)
        valid = np.isfinite(depth)
    z = depth[valid].astype(np.float64)
    sigma = config.axial_sigma_m + config.axial_sigma_per_m2 * z * z
    if np.any(sigma > 0):
        z = z + rng.standard_normal(z.shape) * sigma
    if config.disparity_step_px > 0:
        focal_baseline = intrinsics.fx * config.stereo_baseline_m
        disparity = np.maximum(np.round(focal_baseline / np.maximum(z, 1e-6) / config.disparity_step_px), 1.0)
        z = focal_baseline / (disparity * config.disparity_step_px)
    if config.quantization_step_m > 0:
        z = np.round(z / config.quantization_step_m) * config.quantization_step_m
    z[z <= 0] = np.inf  # noise cannot put a surface behind the camera
    depth[valid] = z.astype(np.float32)
    if config.dropout_probability > 0:
        dropped = rng.random(depth.shape) < config.dropout_probability
        depth[dropped] = np.inf
    no_return = ~np.isfinite(depth)
    out_labels[no_return] = NO_LABEL
    return depth, out_labels


def _flying_pixels(depth: npt.NDArray[np.float32], labels: npt.NDArray[np.int32], config: DepthNoiseConfig,
                   rng: np.random.Generator) -> None:
    """In place: some pixels at depth edges move a random fraction of the way to the other surface."""
    height, width = depth.shape
    # Depth of the 4-neighbour that differs most (finite neighbours only), per pixel.
    padded = np.pad(depth, 1, constant_values=np.inf)
    neighbours = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
    finite = np.isfinite(neighbours) & np.isfinite(depth)[None]
    with np.errstate(invalid="ignore"):
        gap = np.where(finite, np.abs(neighbours - depth[None]), -1.0)
    strongest = np.argmax(gap, axis=0)
    largest_gap = np.take_along_axis(gap, strongest[None], axis=0)[0]
    edge = largest_gap > config.edge_threshold_m
    chosen = edge & (rng.random((height, width)) < config.flying_pixel_probability)
    if not np.any(chosen):
        return
    other = np.take_along_axis(neighbours, strongest[None], axis=0)[0]
    fraction = rng.random(int(chosen.sum())).astype(np.float32)
    depth[chosen] = depth[chosen] + fraction * (other[chosen] - depth[chosen])
    labels[chosen] = NO_LABEL
