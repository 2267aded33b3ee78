"""Do measured keypoints fit a model's kinematics? The constraints `Phi(x)` of a model hold at constant
values along any motion it can make; measured keypoints that break them by more than the noise come
from another mechanism (a wrong link length, a wrong origin), and nothing learned or identified from
them can be trusted."""

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ._constraint import AbstractConstraint, Stack

# RMS deviations up to this many times the noise's RMS effect on a constraint are noise
_NOISE_FACTOR = 3.0
# and below this fraction of the mechanism's size, whatever the noise: the precision of any measurement
_RELATIVE_FLOOR = 1e-6
# samples checked, at most (evenly spread): enough for RMS figures, and one compiled shape
_MAX_SAMPLES = 4096


class ConstraintViolation(ValueError):
    """Measured keypoints break a model's constraints by more than the noise (see
    `cldyn.check_constraints`); the message names the worst constraint and the size of the violation."""


def _leaves(constraint: AbstractConstraint) -> list[AbstractConstraint]:
    if isinstance(constraint, Stack):
        return [leaf for child in constraint.constraints for leaf in _leaves(child)]
    return [constraint]


@eqx.filter_jit
def _values_and_gradients(constraint, x):
    values = jax.vmap(constraint)(x)
    jacobians = jax.vmap(constraint.jacobian)(x[:: max(1, x.shape[0] // 64)])
    return values, jnp.sqrt(jnp.mean(jnp.sum(jacobians**2, axis=-1), axis=0)), jacobians[0]


@dataclasses.dataclass(frozen=True)
class ConstraintCheck:
    """How well measured keypoints keep a model's constraints, one entry per constraint row.

    **Fields:**

    - `labels`: each row's constraint and the keypoints it involves.
    - `measured`: the mean of `Phi(x)` over the data; `level`: the value the model holds it at
      (`None` where only constancy is checked).
    - `deviation`: the RMS of `Phi(x)` about `level` (or about its mean): what the data break it by.
    - `tolerance`: what noise alone would give (`3 noise |grad Phi|`, at least a millionth of the
      mechanism's size).
    - `noise`: the position noise used.
    """

    labels: tuple[str, ...]
    measured: np.ndarray
    level: np.ndarray | None
    deviation: np.ndarray
    tolerance: np.ndarray
    noise: float

    @property
    def violated(self) -> np.ndarray:
        """Per row, whether the deviation exceeds the tolerance."""
        return self.deviation > self.tolerance

    @property
    def ok(self) -> bool:
        """Whether every row holds within its tolerance."""
        return not bool(np.any(self.violated))

    def message(self, what: str = "the model") -> str:
        """A sentence on the worst violation (empty where none)."""
        if self.ok:
            return ""
        worst = int(np.argmax(self.deviation / self.tolerance))
        if self.level is not None:
            values = (
                f"the model holds it at {self.level[worst]:.6g}, the data at {self.measured[worst]:.6g} on "
                "average"
            )
        else:
            values = "it must stay constant along every run"
        count = int(np.sum(self.violated))
        more = f" ({count} of {len(self.labels)} constraint rows are broken)" if count > 1 else ""
        return (
            f"the measured keypoints break {what}'s constraint {self.labels[worst]} by "
            f"{self.deviation[worst]:.3g} (RMS over the data) where noise of {self.noise:.3g} m would "
            f"explain {self.tolerance[worst]:.3g}: {values}{more}"
        )


def check_constraints(
    constraint: AbstractConstraint,
    x: ArrayLike,
    *,
    noise: float,
    level: ArrayLike | None = None,
    keypoint_names: Sequence[str] | None = None,
    what: str = "the model",
    throw: bool = True,
) -> ConstraintCheck:
    """Check that measured keypoints keep a model's holonomic constraints, to within the noise.

    A model's constraints `Phi(x)` stay at their values along any motion it can make (eq. 6 keeps
    `Phi(x(t)) = Phi(x(0))`). For each row, the RMS of `Phi` over the data about the model's `level`
    (or, without one, about its own mean: the row must at least be constant) is compared with what
    position noise alone gives, `3 noise |grad Phi|` (and at least a millionth of the mechanism's
    size). A link of the wrong length breaks a `Distance` row by the difference in length; a pivot
    away from where the model puts it breaks an `Anchor` row by about the offset.

    **Arguments:**

    - `constraint`: the model's constraints (`model.constraint`).
    - `x`: measured keypoint positions, shape `(..., k)` (any number of runs and samples; at most
      4096 of them, evenly spread, are checked).
    - `noise`: the standard deviation of the position noise (metres), e.g. from the data.
    - `level`: the values `Phi` holds in the model, shape `(n,)`, e.g. `Phi(joints.keypoints(q))` for
      any joint coordinates `q`; `None` to check constancy only (models that learn lengths).
    - `keypoint_names`: for the message.
    - `what`: how the message calls the model.
    - `throw`: raise `cldyn.ConstraintViolation` when a row is broken (else only report it).

    **Returns:** a `ConstraintCheck`.

    !!! example

        ```python
        level = model.constraint(joints.keypoints(jnp.zeros(joints.num_joints)))
        cldyn.check_constraints(model.constraint, data.x, noise=0.001, level=level)
        ```
    """
    x = np.asarray(x, dtype=float)
    flat = x.reshape(-1, x.shape[-1])
    if flat.shape[0] > _MAX_SAMPLES:
        flat = flat[np.linspace(0, flat.shape[0] - 1, _MAX_SAMPLES).astype(int)]
    values, gradients, jacobian = (
        np.asarray(a) for a in _values_and_gradients(constraint, jnp.asarray(flat))
    )
    names = list(keypoint_names) if keypoint_names is not None else None
    labels = []
    start = 0
    for leaf in _leaves(constraint):
        rows = leaf.num_constraints
        text = eqx.tree_pformat(leaf, short_arrays=True, width=200).replace("\n", " ")
        for r in range(rows):
            touched = sorted({int(c) // 2 for c in np.flatnonzero(np.abs(jacobian[start + r]) > 0)})
            on = [repr(names[i]) if names is not None and i < len(names) else str(i) for i in touched]
            row = f" row {r}" if rows > 1 else ""
            labels.append(f"{text}{row} (keypoints {', '.join(on)})")
        start += rows
    measured = values.mean(axis=0)
    reference = measured if level is None else np.asarray(level, dtype=float).reshape(-1)
    if reference.shape != measured.shape:
        raise ValueError(
            f"level must have shape {measured.shape}, one per constraint row; got {reference.shape}"
        )
    deviation = np.sqrt(np.mean((values - reference[None, :]) ** 2, axis=0))
    size = float(np.sqrt(np.mean((flat - flat.mean(axis=0)) ** 2))) + float(np.sqrt(np.mean(flat**2)))
    tolerance = _NOISE_FACTOR * float(noise) * gradients + _RELATIVE_FLOOR * max(size, 1e-12)
    check = ConstraintCheck(
        tuple(labels), measured, None if level is None else reference, deviation, tolerance, float(noise)
    )
    if throw and not check.ok:
        raise ConstraintViolation(check.message(what))
    return check
