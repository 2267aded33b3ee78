"""The frames container and its .npz schema, the camera map, and the keypoint-tracking diagnostic."""

import json
import zipfile

import numpy as np
import pytest

import keyvision

EXACT = 1e-12
SAMPLING_TOL = 0.05  # chance correlations and mean differences between 10 fitted and 10 held-out runs


def _frames(runs=4, samples=5, size=8, seed=0) -> keyvision.Frames:
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-np.pi, np.pi, (runs, samples, 1))
    return keyvision.Frames(
        frames=rng.integers(0, 256, (runs, samples, size, size, 3), dtype=np.uint8),
        u=np.repeat(rng.uniform(-2, 2, (runs, 1, 1)), samples, axis=1),
        dt=0.02,
        extras={
            "qpos": angles,
            "qvel": rng.normal(size=(runs, samples, 1)),
            "keypoints": rng.normal(size=(runs, samples, 2)),
        },
        camera=keyvision.PlanarCamera(
            np.array([[1.5, 0.0, 0.1], [0.0, 1.5, 0.6], [0.0, 0.0, 1.0]]), np.eye(3)[[0, 2]]
        ),
        info={"joint_types": ["hinge"], "joint_qpos_index": [0], "validation_runs": 1, "seed": seed},
    )


def test_save_and_load_round_trip(tmp_path):
    frames = _frames()
    path = frames.save(tmp_path / "frames")
    assert path.suffix == ".npz"
    loaded = keyvision.Frames.load(path)
    np.testing.assert_array_equal(loaded.frames, frames.frames)
    assert loaded.frames.dtype == np.uint8
    np.testing.assert_array_equal(loaded.u, frames.u)
    assert loaded.dt == frames.dt and dict(loaded.info) == dict(frames.info)
    assert sorted(loaded.extras) == sorted(frames.extras)
    for name in frames.extras:
        np.testing.assert_array_equal(loaded.extras[name], frames.extras[name])
    np.testing.assert_array_equal(loaded.camera.homography, frames.camera.homography)
    with zipfile.ZipFile(path) as archive:  # plain arrays: nothing needs unpickling
        np.load(path, allow_pickle=False)["metadata"]
        assert "metadata.npy" in archive.namelist()


def test_truncated_file_is_refused_naming_it(tmp_path):
    path = _frames().save(tmp_path / "frames.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=str(path)):
        keyvision.Frames.load(path)


def test_corrupted_bytes_are_refused_naming_the_file(tmp_path):
    path = _frames().save(tmp_path / "frames.npz")
    data = bytearray(path.read_bytes())
    for offset in range(200, len(data) - 200, 97):  # flip bytes inside the compressed members
        data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=str(path)):
        keyvision.Frames.load(path)


def test_files_that_are_no_archive_or_hold_pickles_are_refused_without_advice_to_load_pickles(tmp_path):
    # numpy reads a file that is no zip archive as a pickle and suggests allow_pickle=True, which
    # would run whatever code the file holds; the error names the file and never says that
    cases = {"empty.npz": b"", "random.npz": np.random.default_rng(0).bytes(256), "text.npz": b"frames\n"}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=f"{name}: not an .npz file") as error:
            keyvision.Frames.load(tmp_path / name)
        assert "pickle" not in str(error.value)
    np.savez(tmp_path / "objects.npz", metadata=np.array("{}"), frames=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="objects.npz: entry 'frames' holds pickled Python objects") as error:
        keyvision.Frames.load(tmp_path / "objects.npz")
    assert "allow_pickle" not in str(error.value)


def test_foreign_and_incomplete_files_are_refused(tmp_path):
    other = tmp_path / "other.npz"
    np.savez(other, frames=np.zeros((1, 1, 2, 2, 3), np.uint8))
    with pytest.raises(ValueError, match="no metadata"):
        keyvision.Frames.load(other)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, metadata=np.array(json.dumps({"schema": "cldyn.Sequences/2"})))
    with pytest.raises(ValueError, match="schema"):
        keyvision.Frames.load(wrong)
    partial = tmp_path / "partial.npz"
    np.savez(
        partial,
        metadata=np.array(json.dumps({"schema": "keyvision.Frames/1", "dt": 0.1, "extras": [], "info": {}})),
    )
    with pytest.raises(ValueError, match="missing arrays"):
        keyvision.Frames.load(partial)
    with pytest.raises(FileNotFoundError, match="nothing.npz"):
        keyvision.Frames.load(tmp_path / "nothing.npz")


def test_inconsistent_shapes_are_refused():
    frames = _frames()
    with pytest.raises(ValueError, match="uint8"):
        keyvision.Frames(**{**frames.__dict__, "frames": frames.frames.astype(float)})
    with pytest.raises(ValueError, match="u must have shape"):
        keyvision.Frames(**{**frames.__dict__, "u": frames.u[:2]})
    with pytest.raises(ValueError, match="extras\\['qpos'\\]"):
        keyvision.Frames(**{**frames.__dict__, "extras": {"qpos": np.zeros((1, 5, 1))}})


def test_split_keeps_the_last_runs_for_validation():
    frames = _frames(runs=4)
    train, validation = frames.split()
    assert (train.num_runs, validation.num_runs) == (3, 1)
    np.testing.assert_array_equal(validation.frames, frames.frames[3:])
    np.testing.assert_array_equal(validation.extras["qpos"], frames.extras["qpos"][3:])
    np.testing.assert_allclose(frames.ts, 0.02 * np.arange(5), atol=EXACT)
    assert frames.images().dtype == np.float32 and frames.images().max() <= 1


def test_planar_camera_maps_both_ways():
    tilt = np.array([[1.2, 0.1, 0.3], [-0.05, 0.9, 0.6], [0.02, -0.03, 1.0]])  # projective
    camera = keyvision.PlanarCamera(tilt, np.eye(3)[[0, 2]])
    points = np.random.default_rng(0).uniform(-1, 1, (4, 3, 2))
    np.testing.assert_allclose(camera.to_image(camera.to_plane(points)), points, atol=1e-12)
    u, v = points[0, 0]
    x, y, w = tilt @ np.array([u, v, 1.0])
    np.testing.assert_allclose(camera.to_plane(points[0, 0]), [x / w, y / w], atol=EXACT)


def test_pose_features_are_sin_and_cos_of_hinges():
    frames = _frames()
    features = keyvision.pose_features(frames)
    angles = frames.extras["qpos"][..., 0]
    np.testing.assert_allclose(features, np.stack([np.sin(angles), np.cos(angles)], -1), atol=EXACT)


def test_keypoint_tracking_scores():
    rng = np.random.default_rng(1)
    angles = rng.uniform(-np.pi, np.pi, (20, 10))
    truth = np.stack([np.sin(angles), np.cos(angles), rng.uniform(-1, 1, (20, 10))], axis=-1)
    # Keypoints that are an affine image of the pose (a rotation, scale and offset): R^2 = 1.
    tip = 0.4 * np.stack([truth[..., 0], -truth[..., 1]], -1) @ np.array([[0.8, 0.6], [-0.6, 0.8]]) + 0.1
    cart = np.stack([0.3 * truth[..., 2] - 0.2, np.full(truth.shape[:-1], 0.05)], -1)
    keypoints = np.stack([cart, tip], axis=-2)  # (R, T, K=2, 2)
    assert keyvision.keypoint_tracking(keypoints, truth) == pytest.approx(1.0, abs=1e-9)
    # Keypoints that ignore the pose explain nothing on held-out runs: R^2 near 0 or below.
    noise = rng.normal(size=keypoints.shape)
    assert keyvision.keypoint_tracking(noise, truth) < 0.1
    # A keypoint that sees only the cart explains the cart's third of the variance, not the angle's.
    cart_only = np.stack([cart, cart], axis=-2)
    share = np.var(truth[10:, :, 2]) / np.var(truth[10:], axis=(0, 1)).sum()
    assert keyvision.keypoint_tracking(cart_only, truth) == pytest.approx(share, abs=SAMPLING_TOL)
    with pytest.raises(ValueError, match="leading axes"):
        keyvision.keypoint_tracking(keypoints[:5], truth)
