"""Shared array type aliases for public signatures.

Shapes use the names of the paper: `k` keypoint coordinates (`k = d * n_keypoints`), `n` constraints,
`l` inputs.
"""

from collections.abc import Sequence
from typing import Any, TypeAlias

from jaxtyping import Array, ArrayLike, Float

Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = float | Float[ArrayLike, ""]
Vector: TypeAlias = Float[Array, " k"]
VectorLike: TypeAlias = Float[ArrayLike, " k"]
Matrix: TypeAlias = Float[Array, "k k"]
Control: TypeAlias = Float[Array, " l"]
ControlLike: TypeAlias = Float[ArrayLike, " l"]

# What public functions accept where they convert with `jnp.asarray`: arrays, scalars and nested
# sequences of numbers.
ArrayInput: TypeAlias = ArrayLike | Sequence[Any]
