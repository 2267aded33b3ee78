"""Augment a model with detected effects, and refit it on the weak residual."""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._coordinates import AbstractCoordinate, JointMap
from .._system import ConstrainedLagrangian
from .base import Context
from .residual import Residual
from .result import Detection
from .smoothing import Prepared, TestFunctions


def augment(
    model: ConstrainedLagrangian,
    detections: Sequence[Detection],
    coordinates: Sequence[AbstractCoordinate] | Context,
) -> ConstrainedLagrangian:
    """Add detected effects to a model as cldyn terms, at their estimated values.

    Each effect adds its own term (`JointDamping`, `JointQuadraticDamping`, `JointCoulomb`,
    `JointSpring`, `JointArmature`, a gear factor, `KeypointDrag`, a point mass).

    **Arguments:**

    - `model`: the model to extend.
    - `detections`: the effects (as `identify` returns them).
    - `coordinates`: the joint coordinates that joint effects act through, indexed as in the
      candidates (the values of `identify`'s `joint_coordinates`).

    **Returns:** the augmented `ConstrainedLagrangian`.

    !!! example

        ```python
        result = cldyn.identify(nominal, data, joint_coordinates=coordinates)
        other = cldyn.augment(other_nominal, result.detected, list(coordinates.values()))
        ```
    """
    context = coordinates if isinstance(coordinates, Context) else Context(model, tuple(coordinates))
    for d in detections:
        c = d.candidate
        model = c.effect.augment(model, c, np.asarray(d.theta, dtype=float), context)
    return model


def _refit_filter(model: ConstrainedLagrangian, potential: bool = True):
    """Refit the potential (unless `potential` is false), the dissipation and the armature; the mass
    matrix and the actuator gears stay put, since the equations of motion are homogeneous in
    (M, V, g, F): one of them must fix the scale."""
    spec = jax.tree_util.tree_map(lambda _: False, model)
    parts = [lambda s: s.dissipation, lambda s: s.armature]
    for where in ([lambda s: s.potential] if potential else []) + parts:
        part = where(model)
        if part is None:
            continue
        spec = eqx.tree_at(
            where, spec, jax.tree_util.tree_map(eqx.is_inexact_array, part), is_leaf=lambda v: v is None
        )
    return spec


# Levenberg-Marquardt materialises the (residuals x parameters) Jacobian
_LM_MAX_PARAMETERS = 256


def refit(
    model: ConstrainedLagrangian,
    data: Prepared,
    joints: "JointMap | tuple",
    weights: np.ndarray,
    tests: TestFunctions,
    *,
    kept: np.ndarray | None = None,
    max_steps: int | None = None,
    potential: bool = True,
) -> tuple[ConstrainedLagrangian, optx.RESULTS]:
    """Least-squares refit of the weighted weak joint-space residual (optimistix).

    Levenberg-Marquardt for parametric models; for larger ones (a neural potential), whose Jacobian
    would not fit in memory, BFGS on the sum of squares, which needs gradients only. A refit that
    stops short (at `max_steps`) keeps its last iterate: the caller reports the `result`. `kept`
    `(runs, n)` says which weak equations count (all by default). `potential=False` holds the
    potential fixed.

    **Returns:** `(model, result)`, with the optimistix `RESULTS` of the solve.
    """
    spec = _refit_filter(model, potential)
    params, static = eqx.partition(model, spec)
    size = sum(leaf.size for leaf in jax.tree_util.tree_leaves(params))
    if size == 0:
        return model, optx.RESULTS.successful
    if kept is None:
        kept = np.ones((data.x.shape[0], tests.count), dtype=bool)
    args = (
        static,
        joints,
        data.arrays(),
        (jnp.asarray(tests.psi), jnp.asarray(tests.dpsi)),
        jnp.asarray(weights)[None, None, :] * jnp.asarray(kept, dtype=data.x.dtype)[:, :, None],
    )
    if size <= _LM_MAX_PARAMETERS:
        solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)
        steps = 30 if max_steps is None else max_steps
        solution = optx.least_squares(_weak_residual, solver, params, args, max_steps=steps, throw=False)
    else:
        solver = optx.BFGS(rtol=1e-8, atol=1e-10)
        steps = 500 if max_steps is None else max_steps
        solution = optx.minimise(_sum_of_squares, solver, params, args, max_steps=steps, throw=False)
    return eqx.combine(solution.value, static), solution.result


def _sum_of_squares(params, args):
    residual = _weak_residual(params, args)
    return 0.5 * jnp.sum(residual**2) / residual.shape[0]


def _weak_residual(params, args):
    static, joints, (x, xd, u, q), (psi, dpsi), weights = args
    pieces = jax.vmap(jax.vmap(Residual(eqx.combine(params, static), joints)))(x, xd, u, q)
    momentum, rate, direct = (p[..., 0] for p in pieces)
    weak = (
        -jnp.einsum("nt,rtm->rnm", dpsi, momentum)
        - jnp.einsum("nt,rtm->rnm", psi, rate)
        + jnp.einsum("nt,rtm->rnm", psi, direct)
    )
    return (weak * weights).reshape(-1)
