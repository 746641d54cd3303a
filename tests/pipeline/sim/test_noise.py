"""The depth noise model: each piece does what its parameter says, reproducibly from the seed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.config import ConfigError, from_mapping
from robonav.pipeline.sim.noise import NO_LABEL, DepthNoiseConfig, apply_depth_noise

INTRINSICS = CameraIntrinsics(200, 100, 100.0, 100.0, 99.5, 49.5)
OFF = DepthNoiseConfig(enabled=True, axial_sigma_m=0.0, axial_sigma_per_m2=0.0, dropout_probability=0.0,
                       flying_pixel_probability=0.0)
"""Enabled, every piece off: tests switch on one piece at a time."""


def two_planes() -> tuple[np.ndarray, np.ndarray]:
    """Left half a plane at 1 m (label 3), right half at 2 m (label 5)."""
    depth = np.ones((100, 200), dtype=np.float32)
    depth[:, 100:] = 2.0
    labels = np.full((100, 200), 3, dtype=np.int32)
    labels[:, 100:] = 5
    return depth, labels


def test_disabled_model_returns_the_rendered_frame() -> None:
    depth, labels = two_planes()
    depth[0, 0] = np.nan
    out, out_labels = apply_depth_noise(depth, labels, INTRINSICS, DepthNoiseConfig(enabled=False),
                                        np.random.default_rng(0))
    assert np.isinf(out[0, 0])  # NaN normalised to "no return"
    np.testing.assert_array_equal(out[1:], depth[1:])
    np.testing.assert_array_equal(out_labels, labels)


def test_axial_noise_grows_with_the_square_of_distance() -> None:
    depth, labels = two_planes()
    config = dataclasses.replace(OFF, axial_sigma_m=0.002, axial_sigma_per_m2=0.004)
    out, out_labels = apply_depth_noise(depth, labels, INTRINSICS, config, np.random.default_rng(1))
    near, far = (out - depth)[:, :100], (out - depth)[:, 100:]
    # 10,000 samples each: the sample std is within ~2 % of the true one.
    assert np.std(near) == pytest.approx(0.002 + 0.004 * 1.0, rel=0.05)
    assert np.std(far) == pytest.approx(0.002 + 0.004 * 4.0, rel=0.05)
    assert abs(np.mean(far)) < 0.001
    np.testing.assert_array_equal(out_labels, labels)


def test_dropout_removes_the_configured_fraction_and_their_labels() -> None:
    depth, labels = two_planes()
    out, out_labels = apply_depth_noise(depth, labels, INTRINSICS, dataclasses.replace(OFF, dropout_probability=0.2),
                                        np.random.default_rng(2))
    dropped = ~np.isfinite(out)
    assert dropped.mean() == pytest.approx(0.2, abs=0.02)
    assert np.all(out_labels[dropped] == NO_LABEL)
    np.testing.assert_array_equal(out[~dropped], depth[~dropped])


def test_flying_pixels_appear_only_at_edges_between_the_two_surfaces() -> None:
    depth, labels = two_planes()
    config = dataclasses.replace(OFF, flying_pixel_probability=1.0, edge_threshold_m=0.5)
    out, out_labels = apply_depth_noise(depth, labels, INTRINSICS, config, np.random.default_rng(3))
    changed = out != depth
    assert changed.any()
    assert set(np.nonzero(changed)[1].tolist()) <= {99, 100}  # the two columns along the edge
    assert np.all((out[changed] > 1.0) & (out[changed] < 2.0))
    assert np.all(out_labels[changed] == NO_LABEL)
    high = dataclasses.replace(config, edge_threshold_m=1.5)  # the 1 m step is no longer an edge
    out, _ = apply_depth_noise(depth, labels, INTRINSICS, high, np.random.default_rng(3))
    np.testing.assert_array_equal(out, depth)


def test_quantization_rounds_to_millimetres_and_to_disparity_steps() -> None:
    rng = np.random.default_rng(4)
    depth = rng.uniform(0.5, 2.5, size=(100, 200)).astype(np.float32)
    labels = np.zeros((100, 200), dtype=np.int32)
    out, _ = apply_depth_noise(depth, labels, INTRINSICS, dataclasses.replace(OFF, quantization_step_m=0.001), rng)
    np.testing.assert_allclose(out * 1000.0, np.round(out * 1000.0), atol=1e-3)
    assert np.max(np.abs(out - depth)) <= 0.0005 + 1e-6
    stereo = dataclasses.replace(OFF, disparity_step_px=0.125, stereo_baseline_m=0.05)
    out, _ = apply_depth_noise(depth, labels, INTRINSICS, stereo, rng)
    disparity_steps = INTRINSICS.fx * 0.05 / out / 0.125
    np.testing.assert_allclose(disparity_steps, np.round(disparity_steps), atol=1e-3)
    # The depth step z^2 * step / (f b) grows with distance: far errors exceed near ones.
    error = np.abs(out - depth)
    assert error[depth > 2.0].max() > 4 * error[depth < 1.0].max()


def test_noise_is_reproducible_per_seed_camera_and_frame() -> None:
    depth, labels = two_planes()
    config = DepthNoiseConfig(enabled=True, seed=7)

    def frame(camera: int, number: int, cfg: DepthNoiseConfig = config) -> np.ndarray:
        return apply_depth_noise(depth, labels, INTRINSICS, cfg, cfg.frame_rng(camera, number))[0]

    np.testing.assert_array_equal(frame(0, 1), frame(0, 1))
    assert not np.array_equal(frame(0, 1), frame(0, 2))
    assert not np.array_equal(frame(0, 1), frame(1, 1))
    assert not np.array_equal(frame(0, 1), frame(0, 1, dataclasses.replace(config, seed=8)))


def test_config_is_validated_and_loaded_strictly() -> None:
    loaded = from_mapping(DepthNoiseConfig, {"enabled": True, "dropout_probability": 0.1}, key="sim.noise")
    assert loaded.enabled and loaded.dropout_probability == 0.1
    with pytest.raises(ValueError, match="dropout_probability"):
        DepthNoiseConfig(dropout_probability=1.5)
    with pytest.raises(ValueError, match="axial_sigma_m"):
        DepthNoiseConfig(axial_sigma_m=-0.1)
    with pytest.raises(ConfigError, match="sim.noise.sigma"):
        from_mapping(DepthNoiseConfig, {"sigma": 0.1}, key="sim.noise")
    with pytest.raises(ValueError, match="same"):
        apply_depth_noise(np.ones((2, 2)), np.ones((2, 3), np.int32), INTRINSICS, OFF, np.random.default_rng(0))
