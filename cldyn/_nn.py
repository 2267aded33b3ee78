"""The small multilayer perceptrons of KeyCLD appendix A.4, and Equinox's default initialisation
drawn cheaply.

`jax.random` draws a shaped sample from the flat index of each element, so a draw of shape `(n,)`
reshaped to `shape` gives the same numbers as a draw of `shape`; under JAX's default
`jax_threefry_partitionable` the flat draw compiles several times faster, and a network of a dozen
layers is built in a fraction of the time (`tests/test_nn.py` checks the numbers against Equinox's).
Under that setting element `i` of a threefry draw depends on the key and `i` alone, so the first `n`
elements of a longer draw are the draw of `n`: sizes are rounded up to a power of two, and layers of
different sizes share one compiled draw (every distinct size compiles anew, about 0.1 s on CPU).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

_INIT_STD = 0.01


def _flat(sample, key: PRNGKeyArray, shape: tuple[int, ...], dtype, **kwargs) -> jax.Array:
    size = math.prod(shape)
    drawn = size
    if jax.config.jax_threefry_partitionable and str(jax.random.key_impl(key)) == "threefry2x32":
        drawn = 1 << max(size - 1, 0).bit_length()  # a prefix of the same numbers (module docstring)
    return jax.lax.slice_in_dim(sample(key, (drawn,), dtype, **kwargs), 0, size).reshape(shape)


def default_init(layer, key: PRNGKeyArray):
    """`layer` (an `eqx.nn.Linear` or `eqx.nn.Conv` with one group, possibly abstract as from
    `eqx.filter_eval_shape`) with Equinox's default parameters for `key`: weight and bias uniform in
    `+-1/sqrt(fan_in)`, from the two halves of `key`."""
    wkey, bkey = jax.random.split(key)
    shape, dtype = layer.weight.shape, layer.weight.dtype
    lim = 1 / math.sqrt(math.prod(shape[1:]))
    layer = eqx.tree_at(
        lambda lin: lin.weight, layer, _flat(jax.random.uniform, wkey, shape, dtype, minval=-lim, maxval=lim)
    )
    if layer.bias is None:
        return layer
    bias = _flat(jax.random.uniform, bkey, layer.bias.shape, dtype, minval=-lim, maxval=lim)
    return eqx.tree_at(lambda lin: lin.bias, layer, bias)


def linear(
    in_features: int | str, out_features: int | str, *, dtype=None, key: PRNGKeyArray
) -> eqx.nn.Linear:
    """`eqx.nn.Linear(in_features, out_features, dtype=dtype, key=key)`, the same numbers, built faster."""
    return default_init(
        eqx.filter_eval_shape(eqx.nn.Linear, in_features, out_features, dtype=dtype, key=key), key
    )


def conv2d(
    in_channels: int, out_channels: int, kernel_size: int, *, padding: int, dtype=None, key: PRNGKeyArray
) -> eqx.nn.Conv2d:
    """`eqx.nn.Conv2d(in_channels, out_channels, kernel_size, padding=padding, dtype=dtype, key=key)`,
    the same numbers, built faster."""
    shape = eqx.filter_eval_shape(
        eqx.nn.Conv2d, in_channels, out_channels, kernel_size, padding=padding, dtype=dtype, key=key
    )
    return default_init(shape, key)


def mlp(
    in_size: int, out_size: int | str, width: int, depth: int, *, activation, key: PRNGKeyArray
) -> eqx.nn.MLP:
    """`eqx.nn.MLP(in_size, out_size, width, depth, activation=activation, key=key)`, the same
    numbers, built faster."""
    shape = eqx.filter_eval_shape(eqx.nn.MLP, in_size, out_size, width, depth, activation=activation, key=key)
    keys = jax.random.split(key, depth + 1)
    layers = tuple(default_init(layer, k) for layer, k in zip(shape.layers, keys, strict=True))
    return eqx.tree_at(lambda m: m.layers, shape, layers)


def keycld_mlp(in_size: int, out_size: int | str, width: int, depth: int, *, key: PRNGKeyArray) -> eqx.nn.MLP:
    """A CELU MLP with weights drawn from N(0, 0.01^2) and zero biases, as in appendix A.4."""
    shape = eqx.filter_eval_shape(
        eqx.nn.MLP, in_size, out_size, width, depth, activation=jax.nn.celu, key=key
    )
    keys = jax.random.split(key, len(shape.layers))
    layers = tuple(
        eqx.tree_at(
            lambda lin: (lin.weight, lin.bias),
            layer,
            (
                _INIT_STD * _flat(jax.random.normal, k, layer.weight.shape, layer.weight.dtype),
                jnp.zeros(layer.bias.shape, layer.bias.dtype),
            ),
        )
        for layer, k in zip(shape.layers, keys, strict=True)
    )
    return eqx.tree_at(lambda m: m.layers, shape, layers)
