"""The second-order neural ODE baseline of KeyCLD's ablation study (NODE2, appendix A.4).

It implements `AbstractDynamics`, so `simulate`, the losses, `fit` and `evaluate` take it as they
take KeyCLD's models (`cldyn.keycld_model`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

from ._custom_types import ArrayInput, Vector
from ._nn import mlp
from ._system import AbstractDynamics, check_array


class SecondOrderNeuralODE(AbstractDynamics):
    """A second-order neural ODE, $\\ddot x = f_\\theta(x, \\dot x, u)$: the NODE2 ablation of KeyCLD.

    An MLP on the concatenation `[x, xd, u]` with CELU activations, three hidden layers of
    `2 * 32 = 64` units by default (appendix A.4), that outputs the keypoint accelerations. It has no
    energies and no constraints. Weights use Equinox's default (LeCun-uniform) initialisation.

    **Arguments:**

    - `size`: the number `k` of keypoint coordinates.
    - `num_inputs`: the number `l` of controls (may be 0).
    - `width`: hidden width.
    - `depth`: number of hidden layers.
    - `key`: a `jax.random` key.

    !!! example

        ```python
        node2 = cldyn.SecondOrderNeuralODE(4, 2, key=jax.random.key(0))
        xdd = node2.acceleration(x, xd, u)
        ```
    """

    mlp: eqx.nn.MLP
    dimension: int = eqx.field(static=True)
    inputs: int = eqx.field(static=True)

    def __init__(self, size: int, num_inputs: int, *, width: int = 64, depth: int = 3, key: PRNGKeyArray):
        if size <= 0 or num_inputs < 0 or width <= 0 or depth < 0:
            raise ValueError(
                f"need size > 0, num_inputs >= 0, width > 0, depth >= 0; got {size}, {num_inputs}, "
                f"{width}, {depth}"
            )
        self.mlp = mlp(2 * size + num_inputs, size, width, depth, activation=jax.nn.celu, key=key)
        self.dimension = size
        self.inputs = num_inputs

    @property
    def size(self) -> int:
        return self.dimension

    @property
    def num_inputs(self) -> int:
        return self.inputs

    @property
    def num_constraints(self) -> int:
        return 0

    def acceleration(self, x: ArrayInput, xd: ArrayInput, u: ArrayInput | None = None) -> Vector:
        """The keypoint accelerations `f(x, xd, u)`, shape `(k,)`; `u = None` means zero controls."""
        x = check_array("x", x, (self.size,))
        xd = check_array("xd", xd, (self.size,))
        if u is None:
            u = jnp.zeros(self.num_inputs, dtype=x.dtype)
        u = check_array("u", u, (self.num_inputs,))
        return self.mlp(jnp.concatenate([x, xd, u.astype(x.dtype)]))
