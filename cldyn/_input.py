"""Input matrices `g(x)`: how the controls `u` act on the keypoints (KeyCLD eq. 5)."""

import abc
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from ._coordinates import AbstractCoordinate
from ._custom_types import ArrayInput, Vector
from ._nn import keycld_mlp


class AbstractInputMatrix(eqx.Module):
    """An input matrix `g(x)`, shape `(k, l)`: the generalised force of the controls is `g(x) u`."""

    @property
    @abc.abstractmethod
    def num_inputs(self) -> int:
        """The number `l` of controls."""

    @abc.abstractmethod
    def __call__(self, x: Vector) -> Float[Array, "k l"]:
        """Evaluate `g(x)`.

        **Arguments:**

        - `x`: keypoint coordinates, shape `(k,)`.

        **Returns:** the input matrix, shape `(k, l)`.
        """


class ConstantInput(AbstractInputMatrix):
    """A constant input matrix `g`, for forces along fixed directions; learnable.

    **Arguments:**

    - `matrix`: shape `(k, l)`.
    """

    matrix: Float[Array, "k l"]

    def __check_init__(self):
        if jnp.ndim(self.matrix) != 2:
            raise ValueError(f"input matrix must have shape (k, l), got {jnp.shape(self.matrix)}")

    @property
    def num_inputs(self) -> int:
        return self.matrix.shape[1]

    def __call__(self, x: Vector) -> Float[Array, "k l"]:
        return self.matrix


class JointInput(AbstractInputMatrix):
    """Actuators on joints: column `j` of `g(x)` is `gear_j grad q_j(x)`.

    A motor with torque `u_j` on a hinge with angle `q_j(x)` does virtual work `u_j gear_j dq_j`, which
    in keypoint coordinates is the force `gear_j grad q_j(x) u_j`. The gears are learnable (an actuator
    gain).

    **Arguments:**

    - `coordinates`: the actuated joint coordinates, one per control.
    - `gears`: the gear (gain) of each actuator, shape `(l,)`; ones by default.

    !!! example

        ```python
        g = cldyn.JointInput([cldyn.HingeAngle(child=(None, 0))], gears=[2.0])
        ```
    """

    coordinates: tuple[AbstractCoordinate, ...]
    gears: Float[Array, " l"]

    def __init__(
        self, coordinates: Sequence[AbstractCoordinate], gears: ArrayInput | None = None
    ):
        coordinates = tuple(coordinates)
        for c in coordinates:
            if not isinstance(c, AbstractCoordinate):
                raise TypeError(f"JointInput takes joint coordinates, got {type(c).__name__}")
        self.coordinates = coordinates
        gears = jnp.ones(len(coordinates)) if gears is None else jnp.asarray(gears, dtype=float)
        if gears.shape != (len(coordinates),):
            raise ValueError(
                f"gears must have shape ({len(coordinates)},), one per coordinate; got {gears.shape}"
            )
        self.gears = gears

    @property
    def num_inputs(self) -> int:
        return len(self.coordinates)

    def __call__(self, x: Vector) -> Float[Array, "k l"]:
        if not self.coordinates:
            return jnp.zeros((x.shape[0], 0), dtype=x.dtype)
        grads = jnp.stack([c.gradient(x) for c in self.coordinates], axis=1)
        return grads * self.gears[None, :]


class MLPInput(AbstractInputMatrix):
    """A neural input matrix `g(x)`: KeyCLD appendix A.4.

    **Arguments:**

    - `size`: the number `k` of keypoint coordinates.
    - `num_inputs`: the number `l` of controls.
    - `width`, `depth`: hidden width and number of hidden layers (32 and 2 by default).
    - `key`: a `jax.random` key.
    """

    mlp: eqx.nn.MLP
    size: int = eqx.field(static=True)
    inputs: int = eqx.field(static=True)

    def __init__(
        self, size: int, num_inputs: int, *, width: int = 32, depth: int = 2, key: PRNGKeyArray
    ):
        if size <= 0 or num_inputs <= 0:
            raise ValueError(f"need size > 0 and num_inputs > 0, got {size}, {num_inputs}")
        self.mlp = keycld_mlp(size, size * num_inputs, width, depth, key=key)
        self.size = size
        self.inputs = num_inputs

    @property
    def num_inputs(self) -> int:
        return self.inputs

    def __call__(self, x: Vector) -> Float[Array, "k l"]:
        return self.mlp(x).reshape(self.size, self.inputs)

