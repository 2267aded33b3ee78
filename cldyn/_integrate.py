"""`simulate`: integrate eq. 6 with diffrax and keep the motion on the constraint manifold.

The pieces are diffrax's: the vector field is a `DynamicsTerm`; the solver is any diffrax solver
(`RK4`, `RATTLE` and `RATTLE4` among them) as the stabilisation wraps it (`Projection` projects after
every step, `Baumgarte` feeds the drift back in the term's vector field). `simulate` chooses the
steps, checks the inputs, and reports failures as `diffeqsolve` does.
"""

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Float

from ._control import AbstractControl, as_control, check_control_shape
from ._custom_types import ArrayInput, Vector
from ._solver import DynamicsTerm
from ._solver.projected import ProjectedSolver
from ._stabilisation import AbstractStabilisation, NoStabilisation, Projection
from ._system import AbstractDynamics, ConstrainedLagrangian, check_array

# A state is "clearly" inconsistent beyond this violation, relative to its own scale ...
_CONSISTENCY_RTOL = 1e-6
# ... or beyond this many units in the last place of its dtype, whichever is larger (float32 states
# carry rounding errors of a few ulps, far above 1e-6 of float64).
_CONSISTENCY_ULPS = 1000
# Save times in float32 carry rounding of a few ulps of their magnitude: an interval that exceeds
# `dt0` by less than this many ulps of the largest time is still one step.
_GRID_ULPS = 8


class Trajectory(eqx.Module):
    """A simulated trajectory, sampled at the requested times.

    **Fields:**

    - `ts`: times, shape `(T,)`.
    - `x`: keypoint positions, shape `(T, k)`.
    - `xd`: keypoint velocities, shape `(T, k)`.
    - `u`: the controls applied at those times, shape `(T, l)` (zeros where there was no control).
    - `result`: whether the simulation succeeded, a `diffrax.RESULTS` as in diffrax's
      `Solution.result` (`traj.result == diffrax.RESULTS.successful`). With `simulate(...,
      throw=False)` a failure (a projection that did not converge, too many steps) is reported here;
      states after the failure are not meaningful (diffrax fills them with `inf`).
    """

    ts: Float[Array, " T"]
    x: Float[Array, "T k"]
    xd: Float[Array, "T k"]
    u: Float[Array, "T l"]
    result: dfx.RESULTS


def _tolerance(dtype) -> float:
    return max(_CONSISTENCY_RTOL, _CONSISTENCY_ULPS * float(jnp.finfo(dtype).eps))


def project_state(
    system: ConstrainedLagrangian,
    x: ArrayInput,
    xd: ArrayInput,
    *,
    reference: ArrayInput | None = None,
    projection: Projection = Projection(),
    throw: bool = True,
) -> tuple[Vector, Vector] | tuple[Vector, Vector, dfx.RESULTS]:
    """Make a state consistent with the constraints.

    The positions are projected (mass-weighted, by Newton's method) onto `Phi(x) = reference` when a
    reference is given; otherwise they define the constraint values themselves. The velocities are
    then projected onto `DPhi(x) xd = 0`, removing the part that would stretch the constraints.

    **Arguments:**

    - `system`: the `ConstrainedLagrangian`.
    - `x`, `xd`: positions and velocities, shape `(k,)`.
    - `reference`: the constraint values `Phi` to reach (lengths, for `Distance` and `Anchor`), shape
      `(n,)`; `None` keeps the positions.
    - `projection`: Newton tolerances.
    - `throw`: raise an error if Newton's method does not converge (as `diffrax.diffeqsolve`);
      with `throw=False` the result is returned instead.

    **Returns:** the projected `(x, xd)`; with `throw=False`, `(x, xd, result)` where `result` is a
    `diffrax.RESULTS` (`diffrax.RESULTS.successful` when the positions converged).

    !!! example

        ```python
        system, _ = cldyn.systems.four_bar()
        guess = jnp.array([0.1, 0.5, 1.9, 1.6])
        x, xd = cldyn.project_state(system, guess, jnp.zeros(4), reference=jnp.array([0.5, 2.0, 1.5]))
        ```
    """
    x = check_array("x", x, (system.size,))
    xd = check_array("xd", xd, (system.size,))
    result = dfx.RESULTS.successful
    if system.num_constraints > 0:
        if reference is None:
            xd = DynamicsTerm(system, system.constraint(x)).tangent(x, xd)
        else:
            reference = check_array("reference", reference, (system.num_constraints,))
            x, xd, result = projection.correct(DynamicsTerm(system, reference), x, xd)
    if throw:
        x = result.error_if(x, result != dfx.RESULTS.successful)
        return x, xd
    return x, xd, result


# -- checks and the step grid ------------------------------------------------------------------


def _is_concrete(*values) -> bool:
    return not any(isinstance(v, jax.core.Tracer) for v in jtu.tree_leaves(values))


def _check_inputs(system, x0, xd0, ts, reference, project: bool):
    """Checks on concrete values with messages that say what is wrong and by how much."""
    ts_np = np.asarray(ts)
    if ts_np.ndim != 1 or ts_np.size < 2:
        raise ValueError(f"ts must be a 1-D array of at least two times, got shape {ts_np.shape}")
    if not np.all(np.isfinite(ts_np)):
        raise ValueError("ts contains NaN or infinite times")
    steps = np.diff(ts_np)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0))
        raise ValueError(
            f"ts must be strictly increasing; ts[{i + 1}] = {ts_np[i + 1]} follows ts[{i}] = {ts_np[i]}"
        )
    for name, value in (("x0", x0), ("xd0", xd0)):
        bad = np.flatnonzero(~np.isfinite(np.asarray(value)))
        if bad.size:
            raise ValueError(f"{name} contains NaN or infinite values at indices {bad.tolist()}")
    if project or system.num_constraints == 0:
        return
    tolerance = _tolerance(x0.dtype)
    if reference is not None:
        drift = float(np.max(np.abs(np.asarray(system.constraint(x0)) - np.asarray(reference))))
        scale = max(1.0, float(np.max(np.abs(np.asarray(reference)))))
        if drift > tolerance * scale:
            raise ValueError(
                f"x0 is off the constraint manifold: max |Phi(x0) - reference| = {drift:.3g}. "
                "Pass project=True to project it, or use cldyn.project_state."
            )
    rate = float(np.max(np.abs(np.asarray(system.constraint.velocity(x0, xd0)))))
    scale = max(1.0, float(np.max(np.abs(np.asarray(xd0)))))
    if rate > tolerance * scale:
        raise ValueError(
            f"xd0 violates the constraints: max |DPhi(x0) xd0| = {rate:.3g} (the velocity stretches "
            "a constraint). Pass project=True to project it onto the constraint tangent space, or "
            "use cldyn.project_state."
        )


def _step_grid(ts: np.ndarray, dt0: float) -> np.ndarray:
    """Steps of at most `dt0` that land exactly on every save time, as float64 times."""
    times = ts.astype(np.float64)
    slack = max(1e-9, _GRID_ULPS * float(np.finfo(ts.dtype).eps) * float(np.max(np.abs(times))) / dt0)
    substeps = np.maximum(1, np.ceil(np.diff(times) / dt0 - slack)).astype(int)
    pieces = [np.linspace(a, b, n + 1)[:-1] for a, b, n in zip(times[:-1], times[1:], substeps)]
    return np.concatenate(pieces + [times[-1:]])


def _with_jumps(steps: np.ndarray, jumps: np.ndarray | None, dtype) -> np.ndarray:
    """The step grid `steps` with the jump times of a control inside it added (those within rounding
    of a step already there are not)."""
    if jumps is None:
        return steps
    jumps = np.asarray(jumps, dtype=np.float64)
    jumps = jumps[(jumps > steps[0]) & (jumps < steps[-1])]
    if jumps.size == 0:
        return steps
    scale = max(1.0, float(np.max(np.abs(steps))))
    slack = _GRID_ULPS * float(np.finfo(dtype).eps) * scale
    right = np.clip(np.searchsorted(steps, jumps), 1, steps.size - 1)
    nearest = np.minimum(np.abs(jumps - steps[right - 1]), np.abs(steps[right] - jumps))
    return np.union1d(steps, jumps[nearest > slack])


def _ends_exact(solver: dfx.AbstractSolver) -> bool:
    """Whether the solver's interpolant ends at the (corrected) state that its step returns."""
    return solver.interpolation_cls in (
        dfx.LocalLinearInterpolation,
        dfx.ThirdOrderHermitePolynomialInterpolation.from_k,
    )


def _has_error_estimate(solver: dfx.AbstractSolver) -> bool:
    # `error_order` of an ODE solver does not depend on the terms; an empty PyTree stands for them
    return isinstance(solver, dfx.AbstractAdaptiveSolver) and solver.error_order(None) is not None


def _first_failure(results: dfx.RESULTS) -> dfx.RESULTS:
    """The first unsuccessful result of a batch of results (successful if there is none)."""
    failed = jnp.atleast_1d(results != dfx.RESULTS.successful)
    first = jtu.tree_map(lambda v: jnp.atleast_1d(v)[jnp.argmax(failed)], results)
    return dfx.RESULTS.where(jnp.any(failed), first, dfx.RESULTS.successful)


# -- simulate ------------------------------------------------------------------------------------


_DEFAULT = Projection()


def simulate(
    system: AbstractDynamics,
    x0: ArrayInput,
    xd0: ArrayInput,
    ts: ArrayInput,
    *,
    control: "AbstractControl | ArrayInput | Callable | None" = None,
    solver: dfx.AbstractSolver | None = None,
    stabilisation: AbstractStabilisation | None = _DEFAULT,
    dt0: float | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int | None = None,
    project: bool = False,
    reference: ArrayInput | None = None,
    adjoint: dfx.AbstractAdjoint = dfx.RecursiveCheckpointAdjoint(),
    throw: bool = True,
) -> Trajectory:
    """Integrate the constrained dynamics (eq. 6) from `(x0, xd0)` and sample them at `ts`.

    Built on `diffrax.diffeqsolve` with a `cldyn.DynamicsTerm`: jit-able, vmap-able over initial
    states and parameters, and differentiable end to end (the projections by implicit
    differentiation). Works in float64 and float32 (the dtype of `x0`, `xd0` and the system).

    **Arguments:**

    - `system`: the `ConstrainedLagrangian`, or any other `AbstractDynamics` (a baseline).
    - `x0`, `xd0`: initial positions and velocities, shape `(k,)`. The velocity must satisfy the
      constraints (`DPhi(x0) xd0 = 0`); an initial state that clearly does not (by more than
      `max(1e-6, 1000 eps)` of its scale, `eps` the precision of its dtype) is refused with an error
      that says how far off it is, unless `project=True`.
    - `ts`: strictly increasing save times, shape `(T,)`; the integration runs from `ts[0]` to
      `ts[-1]`.
    - `control`: `None` (no input), any `cldyn.AbstractControl` (`ConstantControl`, `ZeroOrderHold`,
      `EnergyShaping`, ...), or as shorthands a constant `(l,)` array, a function of time `u(t)` or a
      feedback policy `u(t, x, xd)`.
    - `solver`: any diffrax ODE solver, `cldyn.RK4()`, `cldyn.RATTLE()` or `cldyn.RATTLE4()`;
      `diffrax.Tsit5()` by default.
    - `stabilisation`: `Projection()` (default), `Baumgarte(alpha, beta)`, or `None`
      (`NoStabilisation()`). `RATTLE` satisfies the constraints itself: use `None` with it.
    - `dt0`: the step. Adaptive solvers take adaptive steps unless `dt0` is given without
      tolerances; fixed-step solvers take steps of `dt0` (refined so that they land on every save
      time, when `ts` is concrete), or one step per interval of `ts`. A uniform grid `ts` with
      spacing `dt0` takes one step per interval, in float32 too.
    - `rtol`, `atol`: tolerances of the adaptive step controller (1e-6 and 1e-9 by default).
    - `max_steps`: the most steps; by default exactly the fixed steps, or `max(4096, 16 T)`.
    - `project`: project an inconsistent initial state (see `project_state`) instead of refusing it.
    - `reference`: the constraint values to hold, shape `(n,)`; `Phi(x0)` by default.
    - `adjoint`: how to differentiate through the solve (a diffrax adjoint).
    - `throw`: raise an error if the simulation fails (a projection that does not converge, more
      than `max_steps` steps), as `diffrax.diffeqsolve(throw=True)`; with `throw=False` the failure
      is reported in `Trajectory.result`.

    **Returns:** a `Trajectory` with `ts`, `x`, `xd`, the controls `u` at those times, and `result`.

    !!! example

        ```python
        system, joints = cldyn.systems.acrobot()
        x0, xd0 = joints.to_keypoints(jnp.array([2.0, 0.5]), jnp.zeros(2))
        traj = cldyn.simulate(system, x0, xd0, jnp.linspace(0, 10, 1001),
                              solver=cldyn.RK4(), dt0=0.01)
        ```
    """
    if not isinstance(system, AbstractDynamics):
        raise TypeError(
            "system must be a ConstrainedLagrangian (or another AbstractDynamics), "
            f"got {type(system).__name__}"
        )
    stabilisation = NoStabilisation() if stabilisation is None else stabilisation
    if not isinstance(stabilisation, AbstractStabilisation):
        raise TypeError("stabilisation must be Projection(), Baumgarte(alpha, beta) or None")
    x0 = check_array("x0", x0, (system.size,))
    xd0 = check_array("xd0", xd0, (system.size,))
    # Save times given as concrete values stay concrete here even inside a caller's jit (where every
    # jnp operation is staged): the step grid and the input checks need their values.
    concrete_ts = None if isinstance(ts, jax.core.Tracer) else np.asarray(ts)
    ts = jnp.asarray(ts)
    if ts.ndim != 1:
        raise ValueError(f"ts must be a 1-D array of times, got shape {ts.shape}")
    dtype = jnp.result_type(x0.dtype, ts.dtype, float)
    ts = ts.astype(dtype) if concrete_ts is None else jnp.asarray(concrete_ts.astype(dtype))
    if reference is not None:
        reference = check_array("reference", reference, (system.num_constraints,))
    solver = dfx.Tsit5() if solver is None else solver
    control = as_control(control, system.num_inputs)
    check_control_shape(control, system.num_inputs, ts[0], x0, xd0)

    if concrete_ts is not None and _is_concrete(x0, xd0, reference, system):
        _check_inputs(system, x0, xd0, concrete_ts, reference, project)

    can_adapt = _has_error_estimate(solver)
    if not can_adapt and (rtol is not None or atol is not None):
        raise ValueError(
            f"{type(solver).__name__} takes fixed steps and has no error estimate, so rtol/atol do not "
            "apply; give dt0, or use an adaptive solver such as diffrax.Tsit5() or diffrax.Dopri8()"
        )
    adaptive = can_adapt and (dt0 is None or rtol is not None or atol is not None)
    jumps = None if control is None else control.breakpoints()
    grid = None
    if not adaptive and concrete_ts is not None and (dt0 is not None or jumps is not None):
        # step exactly onto every save time, so that saved states are (projected) step ends, and
        # onto every time at which the control jumps, so that no step straddles a jump
        times = concrete_ts.astype(dtype)
        steps = times.astype(np.float64) if dt0 is None else _step_grid(times, dt0)
        grid = jnp.asarray(_with_jumps(steps, jumps, times.dtype), dtype=dtype)
    if adaptive:
        needed = max(4096, 16 * ts.shape[0])
    elif grid is not None:
        needed = grid.shape[0] - 1
    elif dt0 is None:
        needed = ts.shape[0] - 1
    else:  # a traced ts: the number of steps of dt0 is not known here
        needed = max(4096, 16 * ts.shape[0])
    max_steps = needed if max_steps is None else int(max_steps)

    return _simulate(
        system,
        x0,
        xd0,
        ts,
        reference,
        control,
        solver=solver,
        stabilisation=stabilisation,
        adaptive=adaptive,
        grid=grid,
        jumps=None if jumps is None else tuple(float(t) for t in jumps),
        dt0=dt0,
        rtol=1e-6 if rtol is None else rtol,
        atol=1e-9 if atol is None else atol,
        max_steps=max_steps,
        project=project,
        adjoint=adjoint,
        throw=throw,
    )


@eqx.filter_jit
def _simulate(
    system, x0, xd0, ts, reference, control, *, solver, stabilisation, adaptive, grid, jumps, dt0, rtol,
    atol, max_steps, project, adjoint, throw,
):
    result = dfx.RESULTS.successful
    if system.num_constraints > 0:
        if project:
            x0, xd0, result = project_state(system, x0, xd0, reference=reference, throw=False)
        elif not _is_concrete(x0, xd0):
            x0 = eqx.error_if(
                x0,
                ~jnp.all(jnp.isfinite(x0)) | ~jnp.all(jnp.isfinite(xd0)),
                "simulate: the initial state contains NaN or infinite values",
            )
            rate = jnp.max(jnp.abs(system.constraint.velocity(x0, xd0)))
            x0 = eqx.error_if(
                x0,
                rate > _tolerance(x0.dtype) * jnp.maximum(1.0, jnp.max(jnp.abs(xd0))),
                "simulate: xd0 violates the constraints (DPhi(x0) xd0 != 0); pass project=True "
                "or use cldyn.project_state",
            )
        reference = system.constraint(x0) if reference is None else reference
    else:
        reference = None
    term = DynamicsTerm(system, reference, control=control, stabilisation=stabilisation)
    # diffrax sees through one wrapper only (isinstance checks, forward-mode autodiff's scan), so a
    # held control and the stabilisation's correction share one
    if jumps is None:
        wrapped = stabilisation.wrap(solver)
    else:
        wrapped = ProjectedSolver(solver, stabilisation, hold_controls=True)

    if adaptive:
        controller, step = dfx.PIDController(rtol=rtol, atol=atol), dt0
        if jumps:
            controller = dfx.ClipStepSizeController(controller, jump_ts=jnp.asarray(jumps, dtype=ts.dtype))
    elif grid is not None:
        controller, step = dfx.StepTo(grid), None
    elif dt0 is None:
        controller, step = dfx.StepTo(ts), None
    else:  # a traced ts: constant steps, saved states interpolated between them
        controller, step = dfx.ConstantStepSize(), dt0
    controller_grid = controller.ts if isinstance(controller, dfx.StepTo) else None

    # When every step ends on a save time (a uniform grid of spacing dt0, or steps onto ts), diffrax
    # saves each step's end as it goes: no search for the save times inside the step, no interpolation.
    on_steps = (
        controller_grid is not None
        and controller_grid.shape == ts.shape
        and _ends_exact(solver)
        and max_steps >= ts.shape[0] - 1
    )
    solution = dfx.diffeqsolve(
        term,
        wrapped,
        ts[0],
        ts[-1],
        step,
        (x0, xd0),
        saveat=dfx.SaveAt(t0=True, steps=True) if on_steps else dfx.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    result = dfx.RESULTS.where(result == dfx.RESULTS.successful, solution.result, result)
    xs, xds = solution.ys
    if on_steps:  # a buffer of max_steps + 1 states, the steps beyond the last one left empty
        xs, xds = xs[: ts.shape[0]], xds[: ts.shape[0]]
    saves_on_step_ends = not adaptive and (grid is not None or dt0 is None)
    if not (saves_on_step_ends and _ends_exact(solver)):
        # saved states that are interpolated between steps (or by an interpolant that does not end at
        # the corrected state) are corrected too; at a step end this reproduces the step's correction
        xs, xds, corrected = jax.vmap(lambda x, xd: stabilisation.correct(term, x, xd))(xs, xds)
        result = dfx.RESULTS.where(result == dfx.RESULTS.successful, _first_failure(corrected), result)
    if control is None:
        us = jnp.zeros((ts.shape[0], system.num_inputs), dtype=x0.dtype)
    else:
        us = jax.vmap(lambda t, x, xd: jnp.broadcast_to(control(t, x, xd), (system.num_inputs,)))(
            ts, xs, xds
        )
    trajectory = Trajectory(ts=ts, x=xs, xd=xds, u=us, result=result)
    if throw:
        trajectory = result.error_if(trajectory, result != dfx.RESULTS.successful)
    return trajectory
