"""Numbering the keypoints of a trained autoencoder after the roles its constraints give them."""

import itertools
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

import cldyn

from ._model import KeyCLD

_MAX_ASSIGNED = 6  # keypoints: every order is tried (720 at most)


@eqx.filter_jit
def _constraint_spread(constraint, x: Array) -> Array:
    """The mean over runs of the variance over time of each constraint value, `x` `(R, T, k)`."""
    values = jax.vmap(jax.vmap(constraint))(x)
    return jnp.mean(jnp.var(values, axis=1), axis=0)


def assign_keypoints(model: KeyCLD, keypoints: cldyn.Sequences) -> tuple[KeyCLD, tuple[int, ...]]:
    """Number the keypoints of a trained autoencoder so that they keep the dynamics' constraints.

    Stage (a) of `keyvision.train` places the keypoints by reconstruction alone, in no particular
    order, while the constraints of the dynamics give each keypoint a role (in KeyCLD's cart-pole
    keypoint 0 is the cart, whose height is fixed, and keypoint 1 the pole's end at a fixed
    distance from it). Of every order of the keypoints, the one whose constraint values vary least
    within the runs, $\\sum_j \\operatorname{mean}_r \\operatorname{Var}_t \\Phi_j(x_{r,t})$, is
    applied to the estimator's outputs and the renderer's inputs (`permute`): the autoencoder draws
    the same images, with its keypoints renumbered.

    **Arguments:**

    - `model`: a `keyvision.KeyCLD` whose dynamics have constraints (others are returned as given).
    - `keypoints`: the encoded training runs, `cldyn.Sequences` (`keyvision.encode_sequences`).

    **Returns:** `(model, order)`: the renumbered model and the order, keypoint `k` being the old
    keypoint `order[k]`.

    !!! example

        ```python
        model, order = keyvision.assign_keypoints(model, keyvision.encode_sequences(model, data))
        ```
    """
    count = model.num_keypoints
    identity = tuple(range(count))
    constraint = getattr(model.dynamics, "constraint", None)
    if constraint is None or count == 1:
        return model, identity
    if count > _MAX_ASSIGNED:
        warnings.warn(
            f"assign_keypoints: {count} keypoints have {math.factorial(count)} orders; left as they are",
            stacklevel=2,
        )
        return model, identity
    x = jnp.asarray(keypoints.x).reshape(*keypoints.x.shape[:2], count, 2)
    spreads = {
        order: float(jnp.sum(_constraint_spread(constraint, x[:, :, list(order)].reshape(keypoints.x.shape))))
        for order in itertools.permutations(identity)
    }
    order = min(spreads, key=spreads.get)
    if order == identity:
        return model, identity
    return renumbered(model, order), order


def renumbered(model: KeyCLD, order) -> KeyCLD:
    """`model` with keypoint `k` being its keypoint `order[k]`: the order applied to the estimator's
    outputs and the renderer's inputs (`permute`), the dynamics as they are."""
    return KeyCLD(model.estimator.permute(order), model.dynamics, model.renderer.permute(order))
