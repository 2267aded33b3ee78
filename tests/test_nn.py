"""The fast initialisers of `cldyn._nn` draw exactly the numbers Equinox's constructors draw."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cldyn._nn import conv2d, keycld_mlp, linear, mlp


def _same(built, reference):
    built_leaves, built_tree = jax.tree.flatten(eqx.filter(built, eqx.is_array))
    ref_leaves, ref_tree = jax.tree.flatten(eqx.filter(reference, eqx.is_array))
    assert built_tree == ref_tree
    for a, b in zip(built_leaves, ref_leaves, strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    "sizes, dtype", [((3, 5), jnp.float32), ((7, "scalar"), jnp.float64), (("scalar", 4), jnp.float32)]
)
def test_linear_is_equinox_linear(sizes, dtype):
    key = jax.random.key(11)
    _same(linear(*sizes, dtype=dtype, key=key), eqx.nn.Linear(*sizes, dtype=dtype, key=key))


@pytest.mark.parametrize("channels, kernel, dtype", [((3, 8), 3, jnp.float32), ((2, 5), 1, jnp.float64)])
def test_conv2d_is_equinox_conv2d(channels, kernel, dtype):
    key = jax.random.key(12)
    built = conv2d(*channels, kernel, padding=kernel // 2, dtype=dtype, key=key)
    reference = eqx.nn.Conv2d(*channels, kernel, padding=kernel // 2, dtype=dtype, key=key)
    _same(built, reference)
    image = jnp.ones((channels[0], 6, 6), dtype)
    np.testing.assert_array_equal(built(image), reference(image))


@pytest.mark.parametrize("depth, out_size", [(0, "scalar"), (3, 2)])
def test_mlp_is_equinox_mlp(depth, out_size):
    key = jax.random.key(13)
    built = mlp(4, out_size, 6, depth, activation=jax.nn.celu, key=key)
    _same(built, eqx.nn.MLP(4, out_size, 6, depth, activation=jax.nn.celu, key=key))
    assert built.activation is jax.nn.celu


def test_keycld_mlp_draws_normal_weights_and_zero_biases():
    key = jax.random.key(14)
    built = keycld_mlp(4, "scalar", 5, 2, key=key)
    keys = jax.random.split(key, 3)
    shapes = [(5, 4), (5, 5), (1, 5)]
    for layer, k, shape in zip(built.layers, keys, shapes, strict=True):
        np.testing.assert_array_equal(layer.weight, 0.01 * jax.random.normal(k, shape, layer.weight.dtype))
        np.testing.assert_array_equal(layer.bias, np.zeros(shape[0]))
    assert built(jnp.ones(4)).shape == ()


@pytest.mark.parametrize("partitionable", [True, False])
def test_draws_are_equinoxs_under_either_threefry_setting(partitionable):
    # the draws are rounded up to a power of two and cut only where that gives the same numbers (a
    # prefix of a longer partitionable threefry draw); without partitioning they are drawn to size
    previous = jax.config.jax_threefry_partitionable
    jax.config.update("jax_threefry_partitionable", partitionable)
    try:
        key = jax.random.key(15)
        built = mlp(3, 5, 7, 2, activation=jax.nn.relu, key=key)
        _same(built, eqx.nn.MLP(3, 5, 7, 2, activation=jax.nn.relu, key=key))
    finally:
        jax.config.update("jax_threefry_partitionable", previous)
