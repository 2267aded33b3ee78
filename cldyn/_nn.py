"""The small multilayer perceptrons of KeyCLD appendix A.4."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

_INIT_STD = 0.01


def keycld_mlp(
    in_size: int, out_size: int | str, width: int, depth: int, *, key: PRNGKeyArray
) -> eqx.nn.MLP:
    """A CELU MLP with weights drawn from N(0, 0.01^2) and zero biases, as in appendix A.4."""
    mlp = eqx.nn.MLP(in_size, out_size, width, depth, activation=jax.nn.celu, key=key)
    keys = jax.random.split(key, len(mlp.layers))
    layers = tuple(
        eqx.tree_at(
            lambda lin: (lin.weight, lin.bias),
            layer,
            (
                _INIT_STD * jax.random.normal(k, layer.weight.shape, layer.weight.dtype),
                jnp.zeros_like(layer.bias),
            ),
        )
        for layer, k in zip(mlp.layers, keys)
    )
    return eqx.tree_at(lambda m: m.layers, mlp, layers)
