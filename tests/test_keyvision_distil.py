"""Shift distillation: the phase average against closed forms (an equivariant reading is unchanged, a
staircase reading becomes a line), and the distillation bringing one pass onto the average."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
import keyvision

SIZE = 16


class _Bright(keyvision.AbstractKeypointEstimator):
    """Spatial softmax of a scaled colour channel: exactly equivariant to shifts that keep the bright
    pixels inside the frame."""

    num_keypoints: int = 1
    image_size: int = SIZE

    def __call__(self, image):
        return keyvision.spatial_softmax(40.0 * image[None, :, :, 0])


class _Staircase(keyvision.AbstractKeypointEstimator):
    """The brightest pixel's position rounded down to the 4-pixel grid of two 2x2 poolings: a reading
    that stands still between grid lines (its slope in the pose is 0 there) and jumps at them."""

    num_keypoints: int = 1
    image_size: int = SIZE

    def __call__(self, image):
        flat = jnp.argmax(image[:, :, 0])
        row, column = flat // SIZE, flat % SIZE
        row, column = 4 * (row // 4), 4 * (column // 4)
        return jnp.stack([(2 * column + 1) / SIZE - 1, 1 - (2 * row + 1) / SIZE]).astype(jnp.float32)[None]


def _dots(positions):
    images = np.zeros((len(positions), SIZE, SIZE, 3), np.float32)
    for image, (row, column) in zip(images, positions):
        image[row, column] = 1.0
    return jnp.asarray(images)


def _frame(row, column):
    return np.array([(2 * column + 1) / SIZE - 1, 1 - (2 * row + 1) / SIZE])


def test_an_equivariant_reading_is_its_own_average():
    positions = [(5, 6), (8, 9), (10, 4)]  # kept at least 3 pixels from the border by every shift
    images = _dots(positions)
    plain = jax.vmap(_Bright())(images)
    np.testing.assert_allclose(plain[:, 0], [_frame(*p) for p in positions], atol=1e-4)
    np.testing.assert_allclose(keyvision.shift_average(_Bright(), images), plain, atol=1e-5)


def test_the_average_of_a_staircase_is_a_line_of_slope_one():
    # mean over s = 0..3 of (4 floor((p + s) / 4) - s) = p - 1.5 for every integer p: the average
    # reads each pose 1.5 pixels up and left of the truth, and follows it pixel by pixel
    positions = [(r, c) for r in (4, 5, 6, 7, 9) for c in (4, 6, 7, 8, 10)]
    images = _dots(positions)
    staircase = np.asarray(jax.vmap(_Staircase())(images))[:, 0]
    assert len({tuple(np.round(k, 6)) for k in staircase}) < len(positions)  # the steps: poses merged
    average = np.asarray(keyvision.shift_average(_Staircase(), images))[:, 0]
    expected = [_frame(r - 1.5, c - 1.5) for r, c in positions]
    np.testing.assert_allclose(average, expected, atol=1e-6)


def _disc_frames(count=48):
    rng = np.random.default_rng(0)
    frames = np.zeros((count, SIZE, SIZE, 3), np.uint8)
    rows, columns = np.mgrid[:SIZE, :SIZE]
    for frame, angle in zip(frames, rng.uniform(0, 2 * np.pi, count)):
        centre = (SIZE - 1) / 2 + 4.5 * np.array([np.sin(angle), np.cos(angle)])
        frame[(rows - centre[0]) ** 2 + (columns - centre[1]) ** 2 < 4.0] = 255
    return frames


def _tiny_model():
    keys = jax.random.split(jax.random.key(1), 3)
    return keyvision.KeyCLD(
        keyvision.KeypointEstimator(1, width=4, image_size=SIZE, key=keys[0]),
        cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=keys[1], width=8),
        keyvision.Renderer(1, width=4, image_size=SIZE, key=keys[2]),
    )


def test_distillation_brings_one_pass_onto_the_phase_average_and_changes_nothing_else():
    model, frames = _tiny_model(), _disc_frames()
    distilled, report = keyvision.distil_shifts(
        model, frames, key=jax.random.key(0), steps=300, batch_size=16, learning_rate=3e-3
    )
    assert report["frames"] == len(frames) and report["rms_before"] > 0
    # a width-4 U-Net from its initial weights ends near half its distance (0.52 over three keys)
    assert report["rms_after"] < 0.65 * report["rms_before"]
    # measured independently of the report: one pass of the new estimator against the old one's average
    images = jnp.asarray(frames, jnp.float32) / 255
    teacher = keyvision.shift_average(model.estimator, images)
    one_pass = jax.vmap(distilled.estimator)(images)
    distance = float(jnp.sqrt(jnp.mean((one_pass - teacher) ** 2)))
    assert distance == pytest.approx(report["rms_after"], rel=1e-3)
    for part in ("dynamics", "renderer"):
        for a, b in zip(jax.tree.leaves(getattr(model, part)), jax.tree.leaves(getattr(distilled, part))):
            np.testing.assert_array_equal(a, b)


def test_distillation_names_bad_frames():
    model = _tiny_model()
    with pytest.raises(ValueError, match=r"frames must be \(\.\.\., 16, 16, 3\)"):
        keyvision.distil_shifts(model, np.zeros((4, 32, 32, 3), np.uint8), key=jax.random.key(0), steps=1)
    with pytest.raises(ValueError, match="NaN"):
        keyvision.distil_shifts(model, np.full((4, SIZE, SIZE, 3), np.nan), key=jax.random.key(0), steps=1)
    head = model.estimator.unet.head
    broken = eqx.tree_at(lambda m: m.estimator.unet.head.bias, model, jnp.full_like(head.bias, jnp.nan))
    with pytest.raises(FloatingPointError, match="not finite at step 0"):
        keyvision.distil_shifts(broken, _disc_frames(8), key=jax.random.key(0), steps=2, batch_size=4)
    with pytest.raises(TypeError, match="KeyCLD"):
        keyvision.distil_shifts(model.estimator, np.zeros((4, SIZE, SIZE, 3)), key=jax.random.key(0), steps=1)


def test_distil_command_writes_a_model_that_loads_and_keeps_the_dynamics(tmp_path, capsys):
    import json

    from keyvision._cli import main

    frames = keyvision.Frames(
        frames=_disc_frames(12).reshape(3, 4, SIZE, SIZE, 3),
        u=np.zeros((3, 4, 1)),
        dt=0.02,
        extras={},
        camera=keyvision.PlanarCamera(np.eye(3), np.eye(2, 3)),
        info={"scene": "keycld/pendulum", "keypoint_names": ["tip"], "validation_runs": 1},
    )
    data = frames.save(tmp_path / "frames.npz")
    spec = {
        "keypoints": 1, "width": 4, "image_size": SIZE,
        "dynamics": {
            "kind": "keycld", "size": 2, "num_inputs": 1, "constraint": "pendulum", "width": 8, "depth": 1
        },
        "data": {"scene": "keycld/pendulum", "file": "../frames.npz"},
    }
    model = keyvision.model_from_spec(spec, key=jax.random.key(0))
    source = keyvision.save_model(tmp_path / "m", model, spec)
    out = tmp_path / "d"
    argv = ["distil", "--model", source, "--data", data, "--out", out, "--steps", 5, "--batch", 4]
    argv += ["--no-progress"]
    assert main([str(a) for a in argv]) == 0
    said = json.loads(capsys.readouterr().out)
    distilled, record = keyvision.load_model(out)
    assert record["distilled"]["runs"] == 2  # the training runs only: the last run validates
    assert record["distilled"]["rms_after"] == pytest.approx(said["rms_after"])
    assert (out / record["data"]["file"]).resolve() == data.resolve()
    for a, b in zip(jax.tree.leaves(model.dynamics), jax.tree.leaves(distilled.dynamics)):
        np.testing.assert_array_equal(a, b)
    # the same --out again is refused before any work, and the model there is kept
    before = (out / "model.eqx").read_bytes()
    assert main([str(a) for a in argv]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "model.eqx").read_bytes() == before
