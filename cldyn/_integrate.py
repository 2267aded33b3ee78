"""`simulate`: integrate eq. 6 with diffrax and keep the motion on the constraint manifold.

Integrating eq. 6 conserves `Phi(x)` only up to the integrator's error, which accumulates (KeyCLD
appendix A.9). Three remedies, chosen by `stabilisation`:

- `Projection`: after every step, a mass-weighted Newton projection of the positions back onto
  `Phi(x) = Phi(x0)` (optimistix) and of the velocities onto `DPhi(x) xd = 0` (lineax);
- `Baumgarte(alpha, beta)`: feedback on the drift inside the vector field,
  `Phi'' + 2 alpha Phi' + beta^2 (Phi - Phi0) = 0`;
- `None`: plain eq. 6.

`RATTLE` is a constrained symplectic integrator that satisfies both constraints at every step by
construction.
"""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from ._control import AbstractControl, as_control, check_control_shape
from ._custom_types import ArrayInput, Vector
from ._linalg import SmallDense
from ._system import AbstractDynamics, ConstrainedLagrangian, check_array

# A state is "clearly" inconsistent beyond this violation, relative to its own scale.
_CONSISTENCY_RTOL = 1e-6


class Trajectory(eqx.Module):
    """A simulated trajectory, sampled at the requested times.

    **Fields:**

    - `ts`: times, shape `(T,)`.
    - `x`: keypoint positions, shape `(T, k)`.
    - `xd`: keypoint velocities, shape `(T, k)`.
    - `u`: the controls applied at those times, shape `(T, l)` (zeros where there was no control).
    """

    ts: Float[Array, " T"]
    x: Float[Array, "T k"]
    xd: Float[Array, "T k"]
    u: Float[Array, "T l"]


class AbstractStabilisation(eqx.Module):
    """How `simulate` keeps the motion on the constraint manifold."""


class Projection(AbstractStabilisation):
    """Project the state back onto the constraint manifold after every step.

    Positions: the mass-weighted closest point on `Phi(x) = Phi(x0)`, `x + M^-1 DPhi(x)^T lambda`,
    with `lambda` from Newton's method (optimistix) to the tolerance `atol` on `Phi`, in at most
    `max_steps` iterations. Velocities: the mass-weighted projection onto `DPhi(x) xd = 0` (a linear
    solve with lineax). Both projections are differentiable (implicit differentiation).

    **Arguments:**

    - `atol`: tolerance on `|Phi(x) - Phi(x0)|` (and on the Newton update).
    - `rtol`: relative tolerance on the Newton update.
    - `max_steps`: the most Newton iterations per projection.
    """

    atol: float = eqx.field(static=True, default=1e-12)
    rtol: float = eqx.field(static=True, default=1e-10)
    max_steps: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        if not (self.atol > 0 and self.rtol >= 0 and self.max_steps >= 1):
            raise ValueError("Projection needs atol > 0, rtol >= 0 and max_steps >= 1")


class Baumgarte(AbstractStabilisation):
    """Baumgarte stabilisation: `Phi'' + 2 alpha Phi' + beta^2 (Phi - Phi0) = 0` instead of `Phi'' = 0`.

    Cheap (no extra solve), but it only damps the drift; it does not remove it, and too large gains
    make the equations stiff.

    **Arguments:**

    - `alpha`: damping of the constraint velocity (1/s).
    - `beta`: stiffness of the constraint position (1/s).
    """

    alpha: float = eqx.field(static=True)
    beta: float = eqx.field(static=True)

    def __check_init__(self):
        if not (self.alpha >= 0 and self.beta >= 0):
            raise ValueError(f"Baumgarte gains must be non-negative, got {self.alpha}, {self.beta}")


def _project_positions(system: ConstrainedLagrangian, x: Vector, reference: Array, config: Projection):
    jac = system.constraint.jacobian(x)
    minv_jt = system.mass.solve(jac.T)

    def residual(lam, _):
        return system.constraint(x + minv_jt @ lam) - reference

    newton = optx.Newton(rtol=config.rtol, atol=config.atol, linear_solver=SmallDense())
    lam0 = jnp.zeros(system.num_constraints, dtype=x.dtype)
    solution = optx.root_find(residual, newton, lam0, max_steps=config.max_steps, throw=False)
    return x + minv_jt @ solution.value


def _project_velocities(system: ConstrainedLagrangian, x: Vector, xd: Vector) -> Vector:
    jac = system.constraint.jacobian(x)
    minv_jt = system.mass.solve(jac.T)
    operator = lx.MatrixLinearOperator(jac @ minv_jt)
    mu = lx.linear_solve(operator, jac @ xd, SmallDense()).value
    return xd - minv_jt @ mu


def project_state(
    system: ConstrainedLagrangian,
    x: ArrayInput,
    xd: ArrayInput,
    *,
    reference: ArrayInput | None = None,
    projection: Projection = Projection(),
) -> tuple[Vector, Vector]:
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

    **Returns:** the projected `(x, xd)`.

    !!! example

        ```python
        system, _ = cldyn.systems.four_bar()
        guess = jnp.array([0.1, 0.5, 1.9, 1.6])
        x, xd = cldyn.project_state(system, guess, jnp.zeros(4), reference=jnp.array([0.5, 2.0, 1.5]))
        ```
    """
    x = check_array("x", x, (system.size,))
    xd = check_array("xd", xd, (system.size,))
    if system.num_constraints == 0:
        return x, xd
    if reference is not None:
        reference = check_array("reference", reference, (system.num_constraints,))
        x = _project_positions(system, x, reference, projection)
    return x, _project_velocities(system, x, xd)


# -- solvers ---------------------------------------------------------------------------------


_RK4_TABLEAU = dfx.ButcherTableau(
    c=np.array([0.5, 0.5, 1.0]),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
)


class RK4(dfx.AbstractERK):
    """The classical fourth-order Runge-Kutta method, for fixed steps.

    The same scheme as MuJoCo's `RK4` integrator, so that the two can be compared step for step. It
    has no embedded error estimate; use `diffrax.Tsit5` or `diffrax.Dopri8` for adaptive steps.
    """

    tableau: ClassVar[dfx.ButcherTableau] = _RK4_TABLEAU
    interpolation_cls: ClassVar[Callable[..., dfx.AbstractLocalInterpolation]] = (
        dfx.ThirdOrderHermitePolynomialInterpolation.from_k
    )

    def order(self, terms):
        del terms
        return 4


def _forces(system: ConstrainedLagrangian, control: AbstractControl | None, t, x, xd) -> Vector:
    return system._force(x, xd, None if control is None else control(t, x, xd))


# Suzuki's five-stage symmetric composition: fourth order, with an error constant about ten times
# smaller than the three-stage triple jump for the same work per unit of accuracy.
_SUZUKI_W = 1.0 / (4.0 - 4.0 ** (1.0 / 3.0))
_SUZUKI = (_SUZUKI_W, _SUZUKI_W, 1.0 - 4.0 * _SUZUKI_W, _SUZUKI_W, _SUZUKI_W)


class RATTLE(dfx.AbstractSolver):
    """RATTLE: a second-order, symplectic integrator for constrained mechanical systems.

    One step of size `h` from `(x0, v0)`:

    1. `x1 = x0 + h v0 + h^2/2 M^-1 (f(x0) + DPhi(x0)^T lambda)`, with `lambda` such that
       `Phi(x1) = Phi(x0)` (SHAKE; Newton's method via optimistix);
    2. `v1 = (x1 - x0)/h + h/2 M^-1 (f(x1) + DPhi(x1)^T mu)`, with `mu` such that `DPhi(x1) v1 = 0`.

    For conservative forces it preserves the symplectic structure on the constraint manifold: the
    energy error stays bounded instead of drifting. Velocity-dependent forces (damping, feedback
    control) are evaluated with one fixed-point correction, which keeps second order. Fixed steps
    only; it needs a constant mass matrix (no `JointArmature`).

    With `order=4`, each step is Suzuki's symmetric composition of five RATTLE steps of sizes
    `w h, w h, (1 - 4w) h, w h, w h` with `w = 1 / (4 - 4^(1/3))`: still symplectic and on the
    manifold, fourth order, at five times the cost; the energy error shrinks as `h^4` (on a chaotic
    acrobot at `h = 0.01`, from 8e-3 to 3e-5 of the energy above rest).

    **Arguments:**

    - `projection`: tolerances of the Newton solve for `lambda`.
    - `order`: 2 (RATTLE) or 4 (Suzuki's composition of RATTLE).
    """

    projection: Projection = Projection()
    order_: int = eqx.field(static=True, default=2)

    def __init__(self, projection: Projection = Projection(), *, order: int = 2):
        if order not in (2, 4):
            raise ValueError(f"RATTLE comes in order 2 or 4, got {order}")
        self.projection = projection
        self.order_ = order
    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., dfx.LocalLinearInterpolation]] = (
        dfx.LocalLinearInterpolation
    )

    def order(self, terms):
        del terms
        return self.order_

    def init(self, terms, t0, t1, y0, args):
        del terms, t0, t1, y0, args
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del terms, solver_state, made_jump
        if self.order_ == 2:
            y1 = self._rattle(t0, t1, y0, args)
        else:
            y1, start = y0, t0
            for weight in _SUZUKI:
                end = start + weight * (t1 - t0)
                y1 = self._rattle(start, end, y1, args)
                start = end
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful

    def _rattle(self, t0, t1, y0, args):
        system, control, reference = args
        h = t1 - t0
        x0, v0 = y0
        free = x0 + h * v0 + 0.5 * h**2 * system.mass.solve(_forces(system, control, t0, x0, v0))
        if system.num_constraints == 0:
            x1 = free
        else:
            minv_jt = system.mass.solve(system.constraint.jacobian(x0).T)

            def residual(lam, _):
                return system.constraint(free + minv_jt @ lam) - reference

            newton = optx.Newton(
                rtol=self.projection.rtol, atol=self.projection.atol, linear_solver=SmallDense()
            )
            lam0 = jnp.zeros(system.num_constraints, dtype=x0.dtype)
            lam = optx.root_find(
                residual, newton, lam0, max_steps=self.projection.max_steps, throw=False
            ).value
            x1 = free + minv_jt @ lam
        v_half = (x1 - x0) / h

        def kick(v_estimate):
            w = v_half + 0.5 * h * system.mass.solve(_forces(system, control, t1, x1, v_estimate))
            return w if system.num_constraints == 0 else _project_velocities(system, x1, w)

        v1 = kick(v_half)
        if system.dissipation is not None or (control is not None and control.depends_on_state):
            v1 = kick(v1)
        return (x1, v1)

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class _Projected(dfx.AbstractWrappedSolver):
    """Wraps a diffrax solver: every accepted state is projected onto the constraint manifold."""

    solver: dfx.AbstractSolver
    projection: Projection
    # diffrax's adjoints set `scan_kind` on Runge-Kutta solvers (for forward-mode autodiff); it is
    # passed on to the wrapped solver
    scan_kind: str | None = None

    def _inner(self):
        if self.scan_kind is None or getattr(self.solver, "scan_kind", None) is not None:
            return self.solver
        return eqx.tree_at(lambda s: s.scan_kind, self.solver, self.scan_kind, is_leaf=lambda v: v is None)

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1, error, dense_info, solver_state, result = self._inner().step(
            terms, t0, t1, y0, args, solver_state, made_jump
        )
        system, _, reference = args
        x1 = _project_positions(system, y1[0], reference, self.projection)
        xd1 = _project_velocities(system, x1, y1[1])
        y1 = (x1, xd1)
        # the interpolant ends at the projected state, so saved points lie on the manifold
        dense_info = dict(dense_info, y1=y1)
        return y1, error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


def _ends_exact(solver: "_Projected") -> bool:
    """Whether the solver's interpolant ends at the (projected) state it returns."""
    return solver.interpolation_cls in (
        dfx.LocalLinearInterpolation,
        dfx.ThirdOrderHermitePolynomialInterpolation.from_k,
    )


def _vector_field(stabilisation):
    def field(t, y, args):
        system, control, reference = args
        x, xd = y
        u = None if control is None else control(t, x, xd)
        target = None
        if isinstance(stabilisation, Baumgarte) and isinstance(system, ConstrainedLagrangian) and (
            system.num_constraints > 0
        ):
            drift = system.constraint(x) - reference
            rate = system.constraint.velocity(x, xd)
            target = -2 * stabilisation.alpha * rate - stabilisation.beta**2 * drift
        if target is None:
            return xd, system.acceleration(x, xd, u)
        return xd, system._acceleration(x, xd, u, target)

    return field


# -- simulate --------------------------------------------------------------------------------


def _is_concrete(*values) -> bool:
    return not any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(values))


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
    if project or not isinstance(system, ConstrainedLagrangian) or system.num_constraints == 0:
        return
    if reference is not None:
        drift = float(np.max(np.abs(np.asarray(system.constraint(x0)) - np.asarray(reference))))
        scale = max(1.0, float(np.max(np.abs(np.asarray(reference)))))
        if drift > _CONSISTENCY_RTOL * scale:
            raise ValueError(
                f"x0 is off the constraint manifold: max |Phi(x0) - reference| = {drift:.3g}. "
                "Pass project=True to project it, or use cldyn.project_state."
            )
    rate = float(np.max(np.abs(np.asarray(system.constraint.velocity(x0, xd0)))))
    scale = max(1.0, float(np.max(np.abs(np.asarray(xd0)))))
    if rate > _CONSISTENCY_RTOL * scale:
        raise ValueError(
            f"xd0 violates the constraints: max |DPhi(x0) xd0| = {rate:.3g} (the velocity stretches "
            "a constraint). Pass project=True to project it onto the constraint tangent space, or "
            "use cldyn.project_state."
        )


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
) -> Trajectory:
    """Integrate the constrained dynamics (eq. 6) from `(x0, xd0)` and sample them at `ts`.

    Built on `diffrax.diffeqsolve`: jit-able, vmap-able over initial states and parameters, and
    differentiable end to end (the projections by implicit differentiation).

    **Arguments:**

    - `system`: the `ConstrainedLagrangian`, or any other `AbstractDynamics` (a baseline).
    - `x0`, `xd0`: initial positions and velocities, shape `(k,)`. The velocity must satisfy the
      constraints (`DPhi(x0) xd0 = 0`); an initial state that clearly does not is refused with an
      error that says how far off it is, unless `project=True`.
    - `ts`: strictly increasing save times, shape `(T,)`; the integration runs from `ts[0]` to
      `ts[-1]`.
    - `control`: `None` (no input), any `cldyn.AbstractControl` (`ConstantControl`, `ZeroOrderHold`,
      `EnergyShaping`, ...), or as shorthands a constant `(l,)` array, a function of time `u(t)` or a
      feedback policy `u(t, x, xd)`.
    - `solver`: any diffrax ODE solver, `cldyn.RK4()` or `cldyn.RATTLE()`; `diffrax.Tsit5()` by
      default.
    - `stabilisation`: `Projection()` (default), `Baumgarte(alpha, beta)` or `None`. `RATTLE`
      satisfies the constraints itself and ignores it.
    - `dt0`: the step. Adaptive solvers take adaptive steps unless `dt0` is given without
      tolerances; fixed-step solvers take steps of `dt0`, or one step per interval of `ts`.
    - `rtol`, `atol`: tolerances of the adaptive step controller (1e-6 and 1e-9 by default).
    - `max_steps`: the most steps; by default enough for the fixed step, or `max(4096, 16 T)`.
    - `project`: project an inconsistent initial state (see `project_state`) instead of refusing it.
    - `reference`: the constraint values to hold, shape `(n,)`; `Phi(x0)` by default.
    - `adjoint`: how to differentiate through the solve (a diffrax adjoint).

    **Returns:** a `Trajectory` with `ts`, `x`, `xd` and the controls `u` at those times.

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
    if stabilisation is not None and not isinstance(stabilisation, AbstractStabilisation):
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
    if isinstance(solver, RATTLE) and not isinstance(system, ConstrainedLagrangian):
        raise ValueError("RATTLE needs a ConstrainedLagrangian (a mass matrix and forces)")
    if isinstance(solver, RATTLE) and system.armature is not None:
        raise ValueError("RATTLE needs a constant mass matrix; use an RK solver with Projection()")
    if isinstance(solver, RATTLE) and isinstance(stabilisation, Baumgarte):
        raise ValueError("RATTLE satisfies the constraints itself; use stabilisation=None with it")
    control = as_control(control, system.num_inputs)
    check_control_shape(control, system.num_inputs, ts[0], x0, xd0)

    if concrete_ts is not None and _is_concrete(x0, xd0, reference, system):
        _check_inputs(system, x0, xd0, concrete_ts, reference, project)

    # RK4 is an explicit Runge-Kutta method to diffrax, but it has no error estimate
    can_adapt = isinstance(solver, dfx.AbstractAdaptiveSolver) and not isinstance(solver, RK4)
    if not can_adapt and (rtol is not None or atol is not None):
        raise ValueError(
            f"{type(solver).__name__} takes fixed steps and has no error estimate, so rtol/atol do not "
            "apply; give dt0, or use an adaptive solver such as diffrax.Tsit5() or diffrax.Dopri8()"
        )
    adaptive = can_adapt and (dt0 is None or rtol is not None or atol is not None)
    grid = None
    if not adaptive and dt0 is not None and concrete_ts is not None:
        # step exactly onto every save time, so that saved states are (projected) step ends
        times = concrete_ts.astype(float)
        substeps = np.maximum(1, np.ceil(np.diff(times) / dt0 - 1e-9)).astype(int)
        pieces = [np.linspace(a, b, n + 1)[:-1] for a, b, n in zip(times[:-1], times[1:], substeps)]
        grid = jnp.asarray(np.concatenate(pieces + [times[-1:]]), dtype=ts.dtype)
    if adaptive:
        needed = max(4096, 16 * ts.shape[0])
    elif grid is not None:
        needed = grid.shape[0] + 1
    elif dt0 is None:
        needed = ts.shape[0] + 1
    else:
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
        dt0=dt0,
        rtol=1e-6 if rtol is None else rtol,
        atol=1e-9 if atol is None else atol,
        max_steps=max_steps,
        project=project,
        adjoint=adjoint,
    )


@eqx.filter_jit
def _simulate(
    system, x0, xd0, ts, reference, control, *, solver, stabilisation, adaptive, grid, dt0, rtol,
    atol, max_steps, project, adjoint,
):
    constrained = isinstance(system, ConstrainedLagrangian) and system.num_constraints > 0
    if constrained:
        if project:
            x0, xd0 = project_state(system, x0, xd0, reference=reference)
        elif not _is_concrete(x0, xd0):
            x0 = eqx.error_if(
                x0,
                ~jnp.all(jnp.isfinite(x0)) | ~jnp.all(jnp.isfinite(xd0)),
                "simulate: the initial state contains NaN or infinite values",
            )
            rate = jnp.max(jnp.abs(system.constraint.velocity(x0, xd0)))
            x0 = eqx.error_if(
                x0,
                rate > _CONSISTENCY_RTOL * jnp.maximum(1.0, jnp.max(jnp.abs(xd0))),
                "simulate: xd0 violates the constraints (DPhi(x0) xd0 != 0); pass project=True "
                "or use cldyn.project_state",
            )
        reference = system.constraint(x0) if reference is None else reference
    else:
        reference = jnp.zeros(0, dtype=x0.dtype)

    if isinstance(solver, RATTLE):
        wrapped = solver
    elif isinstance(stabilisation, Projection) and constrained:
        wrapped = _Projected(solver, stabilisation)
    else:
        wrapped = solver

    if adaptive:
        controller, step = dfx.PIDController(rtol=rtol, atol=atol), dt0
    elif grid is not None:
        controller, step = dfx.StepTo(grid), None
    elif dt0 is None:
        controller, step = dfx.StepTo(ts), None
    else:  # a traced ts: constant steps, saved states interpolated between them
        controller, step = dfx.ConstantStepSize(), dt0

    solution = dfx.diffeqsolve(
        dfx.ODETerm(_vector_field(stabilisation)),
        wrapped,
        ts[0],
        ts[-1],
        step,
        (x0, xd0),
        args=(system, control, reference),
        saveat=dfx.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
    )
    xs, xds = solution.ys
    saves_on_step_ends = not adaptive and (grid is not None or dt0 is None)
    if isinstance(wrapped, _Projected) and not (saves_on_step_ends and _ends_exact(wrapped)):
        # saved states that are interpolated between steps (or by an interpolant that does not end at
        # the projected state) are projected too; at a step end this reproduces the step's projection
        project = jax.vmap(lambda x, xd: project_state(system, x, xd, reference=reference))
        xs, xds = project(xs, xds)
    if control is None:
        us = jnp.zeros((ts.shape[0], system.num_inputs), dtype=x0.dtype)
    else:
        us = jax.vmap(lambda t, x, xd: jnp.broadcast_to(control(t, x, xd), (system.num_inputs,)))(
            ts, xs, xds
        )
    return Trajectory(ts=ts, x=xs, xd=xds, u=us)

