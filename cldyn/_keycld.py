"""KeyCLD's learnable models (appendix A.4) and the constraint structure of its three scenes."""

import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

from ._constraint import AbstractConstraint, Anchor, Distance, FixedCoordinate, Stack
from ._custom_types import ArrayInput
from ._input import MLPInput
from ._mass import CoupledMasses, PointMasses
from ._potential import MLPPotential
from ._system import ConstrainedLagrangian

KEYCLD_SCENES = ("pendulum", "cartpole", "acrobot")
"""The three scenes of the KeyCLD paper, in the order of its tables."""


def keycld_model(
    size: int,
    num_inputs: int,
    constraint: AbstractConstraint | None,
    *,
    key: PRNGKeyArray,
    masses: ArrayInput | None = None,
    width: int = 32,
    depth: int = 2,
    dim: int = 2,
    mass: str = "point",
) -> ConstrainedLagrangian:
    """The learnable KeyCLD model: point masses (eq. 14), an MLP potential and an MLP input matrix.

    Appendix A.4 of the paper: `V(x)` and `g(x)` are CELU MLPs with two hidden layers of 32 units,
    the masses are learned through their square roots. With `constraint=None` this is the KeyCLD-NC
    ablation.

    **Arguments:**

    - `size`: the number `k` of keypoint coordinates (`dim` per keypoint).
    - `num_inputs`: the number `l` of controls (0 for none: no input matrix).
    - `constraint`: the holonomic constraints, e.g. `cldyn.Anchor(0)` for the pendulum, or `None`.
    - `key`: a `jax.random` key.
    - `masses`: the initial keypoint masses, shape `(size / dim,)`; ones by default.
    - `width`, `depth`: of both MLPs.
    - `dim`: dimension of each keypoint.
    - `mass`: `"point"` for KeyCLD's diagonal point masses (eq. 14), or `"coupled"` for a constant
      mass matrix `A \\otimes I_d` that couples keypoints (`CoupledMasses`), exact for rigid bodies
      whose centre of mass lies between their keypoints.

    **Returns:** a `ConstrainedLagrangian`.

    !!! example

        ```python
        constraint = cldyn.Stack([cldyn.FixedCoordinate(0, axis=1), cldyn.Distance(0, 1)])
        cartpole = cldyn.keycld_model(4, 2, constraint, key=jax.random.key(0))
        nc = cldyn.keycld_model(4, 2, None, key=jax.random.key(0))   # KeyCLD-NC
        ```
    """
    if size <= 0 or size % dim:
        raise ValueError(f"size must be a positive multiple of dim={dim}, got {size}")
    if constraint is not None and not isinstance(constraint, AbstractConstraint):
        raise TypeError(f"constraint must be an AbstractConstraint or None, got {type(constraint).__name__}")
    count = size // dim
    masses = jnp.ones(count) if masses is None else jnp.asarray(masses, dtype=float)
    if masses.shape != (count,):
        raise ValueError(f"masses must have shape ({count},), one per keypoint; got {masses.shape}")
    if mass not in ("point", "coupled"):
        raise ValueError(f"mass must be 'point' or 'coupled', got {mass!r}")
    potential_key, input_key = jax.random.split(key)
    return ConstrainedLagrangian(
        mass=PointMasses(masses, dim=dim) if mass == "point" else CoupledMasses(masses, dim=dim),
        potential=MLPPotential(size, width=width, depth=depth, key=potential_key),
        constraint=constraint,
        input_matrix=None
        if num_inputs == 0
        else MLPInput(size, num_inputs, width=width, depth=depth, key=input_key),
    )



def keycld_constraint(system: str) -> AbstractConstraint:
    """The constraints of KeyCLD's models (paper figure 7), with the pivot at the origin.

    - `"pendulum"`: `Anchor(0)`, the tip at a fixed distance from the pivot;
    - `"cartpole"`: `FixedCoordinate(0, axis=1)` (the cart keeps its height) and `Distance(0, 1)`
      (cart to pole tip);
    - `"acrobot"`: `Anchor(0)` (the elbow) and `Distance(0, 1)` (elbow to tip).

    Only the Jacobians enter the dynamics (eq. 6), so the lengths need not be known.

    !!! example

        ```python
        model = cldyn.keycld_model(4, 2, cldyn.keycld_constraint("acrobot"), key=jax.random.key(0))
        ```
    """
    key = system.removeprefix("keycld/")
    if key == "pendulum":
        return Anchor(0)
    if key == "cartpole":
        return Stack([FixedCoordinate(0, axis=1), Distance(0, 1)])
    if key == "acrobot":
        return Stack([Anchor(0), Distance(0, 1)])
    raise ValueError(f"unknown KeyCLD system {system!r}; choose one of {', '.join(KEYCLD_SCENES)}")
