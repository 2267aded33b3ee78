"""The estimators and renderers of appendix A.4: shapes, translation equivariance, finite gradients."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import keyvision

EQUIVARIANCE_TOL = 1e-4  # float32 sums over 96 x 96 pixels taken in a different order
MASS_ON_DISK = 0.999  # the probe's heatmap must sit on the disk for the keypoint to follow it
SIZE = 96  # the disk must sit farther from the borders than the U-Net's receptive field (~14 px)
RADIUS = 3


def _disk_image(row: int, col: int) -> jnp.ndarray:
    """A bright disk on a constant background: shifting the disk shifts the picture exactly."""
    rows, cols = np.meshgrid(np.arange(SIZE), np.arange(SIZE), indexing="ij")
    disk = ((rows - row) ** 2 + (cols - col) ** 2 <= RADIUS**2).astype(np.float32)
    colour = np.array([0.9, 0.6, 0.2], np.float32)
    background = np.array([0.2, 0.3, 0.4], np.float32)
    return jnp.asarray(background + disk[..., None] * (colour - background))


def _probe(estimator: keyvision.KeypointEstimator, image) -> keyvision.KeypointEstimator:
    """Replace the estimator's last convolution by a matched filter whose logit is +beta/2 on the
    disk's features and -beta/2 on the background's: its keypoint then tracks the disk."""
    features_of = eqx.filter_jit(eqx.tree_at(lambda e: e.unet.head, estimator, replace=lambda x: x).heatmaps)
    features = np.asarray(features_of(image))  # (width, H, W)
    on, off = features[:, SIZE // 2, SIZE // 2], features[:, SIZE // 2, SIZE // 2 + 20]
    direction = (on - off) / np.sum((on - off) ** 2)
    beta = 60.0
    head = estimator.unet.head
    weight = np.zeros(head.weight.shape, np.float32)
    weight[0, :, 1, 1] = beta * direction
    bias = np.full(head.bias.shape, -beta * direction @ (on + off) / 2, np.float32)
    return eqx.tree_at(lambda e: (e.unet.head.weight, e.unet.head.bias), estimator, (weight, bias))


def _mass_near(logits, row, col) -> float:
    weights = np.asarray(jax.nn.softmax(logits.reshape(-1))).reshape(SIZE, SIZE)
    return float(
        weights[row - 2 * RADIUS : row + 2 * RADIUS + 1, col - 2 * RADIUS : col + 2 * RADIUS + 1].sum()
    )


def test_estimator_heatmaps_shift_with_the_image():
    estimator = keyvision.KeypointEstimator(3, width=8, image_size=SIZE, key=jax.random.key(0))
    centre, shift = SIZE // 2, 8  # a multiple of 4: the two 2x2 poolings
    heatmaps_of = eqx.filter_jit(estimator.heatmaps)
    heatmaps = np.asarray(heatmaps_of(_disk_image(centre, centre)))
    moved = np.asarray(heatmaps_of(_disk_image(centre + shift, centre - shift)))
    inside = slice(24, SIZE - 24)
    shifted_inside = slice(24 + shift, SIZE - 24 + shift), slice(24 - shift, SIZE - 24 - shift)
    np.testing.assert_allclose(
        moved[:, shifted_inside[0], shifted_inside[1]], heatmaps[:, inside, inside], atol=EQUIVARIANCE_TOL
    )


@pytest.mark.parametrize("drow, dcol", [(0, 4), (0, -8), (8, 0), (-4, 4)])
def test_estimator_keypoints_move_with_the_image(drow, dcol):
    """Shifting the picture by k pixels moves the keypoint by 2k / size (x right, y up)."""
    centre = SIZE // 2
    estimator = keyvision.KeypointEstimator(1, width=8, image_size=SIZE, key=jax.random.key(1))
    estimator = _probe(estimator, _disk_image(centre, centre))
    before, after = _disk_image(centre, centre), _disk_image(centre + drow, centre + dcol)
    heatmaps_of, keypoints_of = eqx.filter_jit(estimator.heatmaps), eqx.filter_jit(estimator)
    assert _mass_near(heatmaps_of(before), centre, centre) > MASS_ON_DISK
    assert _mass_near(heatmaps_of(after), centre + drow, centre + dcol) > MASS_ON_DISK
    motion = np.asarray(keypoints_of(after) - keypoints_of(before))[0]
    np.testing.assert_allclose(motion, [2 * dcol / SIZE, -2 * drow / SIZE], atol=EQUIVARIANCE_TOL)


PAIRS = [
    (keyvision.KeypointEstimator, keyvision.Renderer),
    (keyvision.KeypointEstimatorFC, keyvision.RendererFC),
]


@pytest.mark.parametrize("estimator_type, renderer_type", PAIRS)
def test_autoencoder_shapes_ranges_and_finite_gradients(estimator_type, renderer_type):
    size, count = 32, 2
    ekey, rkey, ikey = jax.random.split(jax.random.key(2), 3)
    estimator = estimator_type(count, width=8, image_size=size, key=ekey)
    renderer = renderer_type(count, width=8, image_size=size, key=rkey)
    images = jax.random.uniform(ikey, (3, size, size, 3), jnp.float32)

    def loss(networks, images):
        estimator, renderer = networks
        return jnp.mean((jax.vmap(lambda image: renderer(estimator(image)))(images) - images) ** 2)

    batched = eqx.filter_jit(lambda network, inputs: jax.vmap(network)(inputs))
    keypoints = batched(estimator, images)
    assert keypoints.shape == (3, count, 2) and keypoints.dtype == jnp.float32
    reconstruction = batched(renderer, keypoints)
    assert reconstruction.shape == (3, size, size, 3) and reconstruction.dtype == jnp.float32
    assert jnp.all((reconstruction > 0) & (reconstruction < 1))
    grads = eqx.filter_jit(eqx.filter_grad(loss))((estimator, renderer), images)
    leaves = jax.tree_util.tree_leaves(eqx.filter(grads, eqx.is_inexact_array))
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    for part in grads:  # both networks learn
        assert any(
            float(jnp.abs(leaf).max()) > 0
            for leaf in jax.tree_util.tree_leaves(eqx.filter(part, eqx.is_inexact_array))
        )


def test_unet_keypoints_lie_in_the_image_frame():
    estimator = keyvision.KeypointEstimator(4, width=8, image_size=32, key=jax.random.key(3))
    keypoints = eqx.filter_jit(estimator)(jax.random.uniform(jax.random.key(4), (32, 32, 3), jnp.float32))
    assert keypoints.shape == (4, 2) and bool(jnp.all(jnp.abs(keypoints) < 1))


def test_renderer_draws_its_learned_constant_and_gaussian_maps():
    renderer = keyvision.Renderer(2, width=8, image_size=32, sigma=0.1, key=jax.random.key(5))
    assert renderer.constant.shape == (6, 32, 32)  # width - keypoints channels by default
    other = keyvision.Renderer(2, width=8, image_size=32, constant_channels=3, key=jax.random.key(5))
    assert other.constant.shape == (3, 32, 32)


def test_wrong_shapes_and_sizes_are_refused():
    estimator = keyvision.KeypointEstimator(2, width=8, image_size=32, key=jax.random.key(0))
    with pytest.raises(ValueError, match="one image of shape"):
        estimator(jnp.zeros((2, 32, 32, 3), jnp.float32))
    renderer = keyvision.Renderer(2, width=8, image_size=32, key=jax.random.key(0))
    with pytest.raises(ValueError, match="shape \\(2, 2\\)"):
        renderer(jnp.zeros((3, 2), jnp.float32))
    with pytest.raises(ValueError, match="multiple of 16"):
        keyvision.KeypointEstimatorFC(2, image_size=40, key=jax.random.key(0))
    with pytest.raises(ValueError, match="multiple of 4"):
        keyvision.Renderer(2, image_size=30, key=jax.random.key(0))
    with pytest.raises(ValueError, match="width"):
        keyvision.KeypointEstimator(2, width=0, key=jax.random.key(0))


# -- model files ---------------------------------------------------------------------------------

SPEC = {
    "keypoints": 2,
    "width": 4,
    "image_size": 16,
    "dynamics": {
        "kind": "keycld",
        "size": 4,
        "num_inputs": 1,
        "constraint": "acrobot",
        "width": 8,
        "depth": 1,
    },
}


def test_saved_model_loads_bitwise_and_bad_files_are_refused(tmp_path):
    model = keyvision.model_from_spec(SPEC, key=jax.random.key(3))
    assert {a.dtype for a in jax.tree.leaves(eqx.filter(model, eqx.is_inexact_array))} == {
        jnp.dtype("float32")
    }
    # perturb the parameters so that a rebuilt untrained model could not pass for the saved one
    model = jax.tree.map(lambda a: a + 0.5 if eqx.is_inexact_array(a) else a, model)
    keyvision.save_model(tmp_path / "m", model, {**SPEC, "note": "kept"})
    loaded, spec = keyvision.load_model(tmp_path / "m")
    assert spec["note"] == "kept"
    for a, b in zip(
        jax.tree.leaves(eqx.filter(model, eqx.is_array)), jax.tree.leaves(eqx.filter(loaded, eqx.is_array))
    ):
        assert a.dtype == b.dtype and np.array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(FileNotFoundError, match="no such directory"):
        keyvision.load_model(tmp_path / "nothing")
    with pytest.raises(ValueError, match="does not match"):
        keyvision.save_model(tmp_path / "other", model, {**SPEC, "width": 8})
    assert not (tmp_path / "other").exists()
    with pytest.raises(KeyError, match="image_size"):
        keyvision.model_from_spec({k: v for k, v in SPEC.items() if k != "image_size"}, key=jax.random.key(0))
    # a truncated parameter file, then a description whose sizes do not fit the parameters
    parameters = (tmp_path / "m" / "model.eqx").read_bytes()
    (tmp_path / "m" / "model.eqx").write_bytes(parameters[: len(parameters) // 2])
    with pytest.raises(ValueError, match="model.eqx: cannot load"):
        keyvision.load_model(tmp_path / "m")
    (tmp_path / "m" / "model.eqx").write_bytes(parameters)
    (tmp_path / "m" / "keyvision.json").write_text(json.dumps({**SPEC, "width": 8}))
    with pytest.raises(ValueError, match="model.eqx: cannot load"):
        keyvision.load_model(tmp_path / "m")
    (tmp_path / "m" / "keyvision.json").write_text("{not json")
    with pytest.raises(ValueError, match="keyvision.json: unreadable"):
        keyvision.load_model(tmp_path / "m")
