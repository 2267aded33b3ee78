"""Renumbering keypoints: every estimator and renderer permuted together draws the same images with
the keypoints renumbered, and the assignment finds the order in which keypoints keep the cart-pole's
constraints (the cart at a fixed height, the pole's end at a fixed distance from it)."""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
import keyvision

SIZE = 16
ROUNDING = 1e-5  # float32 networks: the same sums in another order
PAIRS = [
    (keyvision.KeypointEstimator, keyvision.Renderer),
    (keyvision.KeypointEstimatorFC, keyvision.RendererFC),
]


@pytest.mark.parametrize(("estimator_cls", "renderer_cls"), PAIRS)
def test_permuted_networks_renumber_the_keypoints_and_draw_the_same(estimator_cls, renderer_cls):
    keys = jax.random.split(jax.random.key(0), 4)
    estimator = estimator_cls(3, width=8, image_size=SIZE, key=keys[0])
    renderer = renderer_cls(3, width=8, image_size=SIZE, key=keys[1])
    images = jax.random.uniform(keys[2], (2, SIZE, SIZE, 3), jnp.float32)
    points = jax.random.uniform(keys[3], (2, 3, 2), jnp.float32, -0.8, 0.8)

    @eqx.filter_jit
    def run(estimator, renderer):
        return jax.vmap(estimator)(images), jax.vmap(renderer)(points)

    found, drawn = run(estimator, renderer)
    for order in itertools.permutations(range(3)):
        order = list(order)
        new_found, _ = run(estimator.permute(order), renderer)
        np.testing.assert_allclose(new_found, found[:, order], atol=ROUNDING)
        # the renumbered renderer, given the renumbered keypoints, draws what the old one drew
        renumbered = eqx.filter_jit(jax.vmap(renderer.permute(order)))(points[:, order])
        np.testing.assert_allclose(renumbered, drawn, atol=ROUNDING)
    with pytest.raises(ValueError, match="permutation of 0..2"):
        estimator.permute([0, 0, 1])
    with pytest.raises(ValueError, match="permutation of 0..2"):
        renderer.permute([0, 1])


def _cartpole_keypoints(runs=6, samples=20, *, cart_first: bool):
    """Keypoints of a cart sliding at height -0.1 and a pole of length 0.5 turning on it."""
    rng = np.random.default_rng(0)
    t = np.arange(samples) * 0.05
    cart = rng.uniform(-0.5, 0.5, (runs, 1)) + 0.3 * np.sin(2 * t + rng.uniform(0, 6, (runs, 1)))
    angle = rng.uniform(-3, 3, (runs, 1)) + 2 * t
    tip = np.stack([cart + 0.5 * np.sin(angle), -0.1 + 0.5 * np.cos(angle)], axis=-1)
    base = np.stack([cart, np.full_like(cart, -0.1)], axis=-1)
    pair = (base, tip) if cart_first else (tip, base)
    return np.concatenate(pair, axis=-1).astype(np.float32)


def test_assign_keypoints_finds_the_order_that_keeps_the_constraints():
    keys = jax.random.split(jax.random.key(1), 3)
    model = keyvision.KeyCLD(
        keyvision.KeypointEstimator(2, width=8, image_size=SIZE, key=keys[0]),
        cldyn.keycld_model(4, 1, cldyn.keycld_constraint("cartpole"), key=keys[1], width=8),
        keyvision.Renderer(2, width=8, image_size=SIZE, key=keys[2]),
    )
    swapped = cldyn.Sequences(_cartpole_keypoints(cart_first=False), None, 0.05)
    renumbered, order = keyvision.assign_keypoints(model, swapped)
    assert order == (1, 0)
    images = jax.random.uniform(jax.random.key(2), (3, SIZE, SIZE, 3), jnp.float32)
    encode = eqx.filter_jit(lambda m, z: m.encode(z))
    expected = encode(model, images)[:, [2, 3, 0, 1]]
    np.testing.assert_allclose(encode(renumbered, images), expected, atol=ROUNDING)
    in_order = cldyn.Sequences(_cartpole_keypoints(cart_first=True), None, 0.05)
    same, order = keyvision.assign_keypoints(model, in_order)
    assert order == (0, 1) and same is model
    # no constraints, nothing to go by
    free = eqx.tree_at(lambda m: m.dynamics, model, cldyn.keycld_model(4, 1, None, key=keys[1], width=8))
    assert keyvision.assign_keypoints(free, swapped)[1] == (0, 1)


class _TwoCorners(keyvision.AbstractKeypointEstimator):
    """A hand-written estimator that does not implement `permute`."""

    num_keypoints: int = 2
    image_size: int = 16

    def __call__(self, image):
        return jnp.array([[-0.5, -0.5], [0.5, 0.5]]) + 0.0 * image.mean()


def test_an_estimator_without_permute_keeps_the_identity_and_refuses_a_renumbering():
    estimator = _TwoCorners()
    assert estimator.permute([0, 1]) is estimator
    with pytest.raises(NotImplementedError, match=r"_TwoCorners does not implement permute.*\[1, 0\]"):
        estimator.permute([1, 0])
    with pytest.raises(ValueError, match="permutation of 0..1"):
        estimator.permute([0, 0])
