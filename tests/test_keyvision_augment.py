"""Dihedral augmentation: the eight symmetries of the square against closed forms (where a pixel goes,
where a blob's keypoint goes), and an exactly equivariant estimator that encodes the same keypoints
with and without augmentation, through the batching that draws the transforms."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
import keyvision

SIZE = 16
EXACT = 1e-6  # float32 keypoints: sums of 256 weighted pixel centres
POINTS = np.array([[0.3, -0.55], [-0.7, 0.2]])
# (x, y) -> image-frame image of the point under each transform, written out by hand: quarter turns
# counter-clockwise (x, y) -> (-y, x), after a left-right mirror (x, y) -> (-x, y) for g >= 4.
BY_HAND = [
    lambda x, y: (x, y),
    lambda x, y: (-y, x),
    lambda x, y: (-x, -y),
    lambda x, y: (y, -x),
    lambda x, y: (-x, y),
    lambda x, y: (-y, -x),
    lambda x, y: (x, -y),
    lambda x, y: (y, x),
]


def test_a_pixel_moves_where_the_transform_sends_its_centre():
    row, col = 3, 11
    image = jnp.zeros((SIZE, SIZE, 1)).at[row, col, 0].set(1.0)
    x, y = np.asarray(keyvision.pixel_to_frame(jnp.array([row, col], jnp.float32), SIZE, SIZE))
    for g, by_hand in enumerate(BY_HAND):
        moved = np.asarray(keyvision.transform_images(image[None], jnp.array([g]))[0, ..., 0])
        lit = np.argwhere(moved == 1.0)
        expected = np.asarray(keyvision.frame_to_pixel(jnp.array(by_hand(x, y)), SIZE, SIZE))
        np.testing.assert_allclose(lit, [np.round(expected)], atol=0, err_msg=f"transform {g}")


def test_restore_keypoints_undoes_each_transform_of_a_blob():
    maps = keyvision.gaussian_maps(jnp.asarray(POINTS, jnp.float32), SIZE, SIZE, sigma=0.1)
    image = jnp.moveaxis(maps, 0, -1)  # two channels, one blob each
    # the blob near the border is cut off by it: its keypoint lies a little off the point, and its
    # transformed keypoint just as far off the transformed point (the pixel grid is symmetric)
    plain = np.asarray(keyvision.spatial_softmax(jnp.log(maps)))
    np.testing.assert_allclose(plain, POINTS, atol=1e-3)
    for g, by_hand in enumerate(BY_HAND):
        seen = keyvision.transform_images(image[None], jnp.array([g]))[0]
        found = keyvision.spatial_softmax(jnp.log(jnp.moveaxis(seen, -1, 0)))
        np.testing.assert_allclose(found, [by_hand(*p) for p in plain], atol=EXACT, err_msg=f"{g}")
        back = keyvision.restore_keypoints(found, jnp.array(g))
        np.testing.assert_allclose(back, plain, atol=EXACT, err_msg=f"transform {g}")


class _BrightestChannel(keyvision.AbstractKeypointEstimator):
    """Spatial softmax of a scaled colour channel: exactly equivariant to every pixel permutation that
    maps the pixel grid onto itself."""

    num_keypoints: int = 1
    image_size: int = SIZE

    def __call__(self, image):
        return keyvision.spatial_softmax(30.0 * image[None, :, :, 0])


def test_an_equivariant_estimator_encodes_the_same_under_augmentation():
    keys = jax.random.split(jax.random.key(0), 4)
    model = keyvision.KeyCLD(
        _BrightestChannel(),
        cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=keys[0], width=8),
        keyvision.Renderer(1, width=8, image_size=SIZE, key=keys[1]),
    )
    frames = jax.random.uniform(keys[2], (6, 5, SIZE, SIZE, 3))
    data = keyvision.ImageSequences(frames, jnp.zeros((6, 1)), 0.1)
    batching = keyvision.Augment(cldyn.Windows(4, 3))
    batching.check(data)
    batch = eqx.filter_jit(batching.draw)(data, keys[3])
    assert batch.transforms.shape == (4, 3) and batch.frames.shape == (4, 3, SIZE, SIZE, 3)
    assert int(batch.transforms.min()) >= 0 and int(batch.transforms.max()) < 8
    assert len(np.unique(np.asarray(batch.transforms))) > 1  # 12 draws of 8: not all the same
    plain = model.encode(batch.frames)
    augmented = model.encode(batch.frames, batch.transforms)
    np.testing.assert_allclose(augmented, plain, atol=EXACT)
    loss = keyvision.Reconstruction()
    unaugmented = keyvision.ImageSequences(batch.frames, batch.u, batch.dt)
    np.testing.assert_allclose(loss(model, batch), loss(model, unaugmented), rtol=1e-5)


def test_a_convolutional_estimator_is_not_equivariant_until_trained():
    """The U-Net estimator at initialisation gives other keypoints for a turned frame: augmentation
    changes what the losses see (so the test above is not vacuous)."""
    estimator = keyvision.KeypointEstimator(1, width=8, image_size=SIZE, key=jax.random.key(1))
    model = keyvision.KeyCLD(
        estimator,
        cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=jax.random.key(2), width=8),
        keyvision.Renderer(1, width=8, image_size=SIZE, key=jax.random.key(3)),
    )
    frames = jax.random.uniform(jax.random.key(4), (3, SIZE, SIZE, 3), jnp.float32)
    encode = eqx.filter_jit(lambda model, frames, transforms: model.encode(frames, transforms))
    turned = encode(model, frames, jnp.array([1, 2, 5]))
    assert float(jnp.max(jnp.abs(turned - encode(model, frames, None)))) > 1e-3


def test_augment_refuses_other_data_and_bad_transforms():
    with pytest.raises(TypeError, match="ImageSequences"):
        keyvision.Augment(cldyn.Windows(2, 1)).check(cldyn.Sequences(jnp.zeros((3, 5, 2)), None, 0.1))
    with pytest.raises(TypeError, match="cldyn batching"):
        keyvision.Augment("windows")
    with pytest.raises(ValueError, match="transforms must have shape"):
        keyvision.ImageSequences(np.zeros((2, 3, 4, 4, 3)), None, 0.1, transforms=np.zeros((2, 4), int))
    with pytest.raises(ValueError, match="square"):
        keyvision.transform_images(jnp.zeros((1, 4, 6, 3)), jnp.zeros((1,), int))
