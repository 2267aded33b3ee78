"""Constraint stabilisation: how a simulation stays on the manifold `Phi(x) = Phi(x0)` (KeyCLD A.9).

Eq. 6 keeps `d2/dt2 Phi = 0` exactly, but an integrator conserves `Phi` only up to its error, which
accumulates. A stabilisation acts in one or both of two places, through two abstract methods:

- `feedback`: a drift feedback inside the vector field (`Baumgarte`);
- `correct`: a correction of the state after every step (`Projection`), applied by wrapping the
  solver (`wrap`).

`NoStabilisation` does neither.
"""

import abc
from typing import TYPE_CHECKING

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from ._custom_types import Vector
from ._linalg import SmallDense, small_matmul, small_solve

if TYPE_CHECKING:
    from ._solver.term import DynamicsTerm

# A tolerance finer than the rounding of the state's own dtype cannot be met: tolerances are never
# tighter than this many units in the last place of the values they compare.
ROUNDOFF_ULPS = 64


class AbstractStabilisation(eqx.Module):
    """How a simulation keeps the motion on the constraint manifold `Phi(x) = Phi(x0)`.

    A stabilisation may add a feedback on the drift to the vector field (`feedback`), correct the
    state after every step (`correct`, applied by the solver that `wrap` returns), or both.
    """

    @abc.abstractmethod
    def feedback(self, term: "DynamicsTerm", x: Vector, xd: Vector) -> Float[Array, " n"] | None:
        """The value that the vector field drives the constraint acceleration
        $D\\Phi \\ddot x + \\langle D^2\\Phi, \\dot x\\rangle \\dot x$ to, shape `(n,)`; `None` for zero
        (eq. 6 unchanged)."""

    @abc.abstractmethod
    def correct(
        self, term: "DynamicsTerm", x: Vector, xd: Vector
    ) -> tuple[Vector, Vector, dfx.RESULTS]:
        """The state `(x, xd)` after a step as this stabilisation leaves it, and whether the
        correction succeeded (a `diffrax.RESULTS`)."""

    @abc.abstractmethod
    def correct_step(
        self, term: "DynamicsTerm", x: Vector, xd: Vector
    ) -> tuple[Vector, Vector, dfx.RESULTS]:
        """`correct` for a state that a step of the integrator has just reached from a state on the
        manifold (so within the step's local error of it), as cheaply as that allows."""

    @abc.abstractmethod
    def wrap(self, solver: dfx.AbstractSolver) -> dfx.AbstractSolver:
        """The solver that integrates with this stabilisation: `solver` itself, or a wrapper around it
        that applies `correct_step` after every step."""


class NoStabilisation(AbstractStabilisation):
    """Plain eq. 6: no feedback, no correction. The constraints drift with the integrator's error.

    `simulate(..., stabilisation=None)` means this. It is what `RATTLE` needs, since it satisfies the
    constraints itself.
    """

    def feedback(self, term, x, xd) -> None:
        del term, x, xd
        return None

    def correct(self, term, x, xd):
        del term
        return x, xd, dfx.RESULTS.successful

    def correct_step(self, term, x, xd):
        return self.correct(term, x, xd)

    def wrap(self, solver: dfx.AbstractSolver) -> dfx.AbstractSolver:
        return solver


class Projection(AbstractStabilisation):
    """Project the state back onto the constraint manifold after every step.

    Positions: the mass-weighted closest point on `Phi(x) = Phi(x0)`, `x + M^-1 DPhi(x)^T lambda`,
    with `lambda` from Newton's method. After a step the state is within the integrator's local
    error of the manifold, where Newton's method converges quadratically, so the correction takes a
    fixed number of iterations (`iterations`), unrolled: no loop and no convergence test between
    iterations, which XLA fuses into a few kernels. A correction whose residual still exceeds `atol`
    is reported as a failure in the simulation's `result`. Other projections (`cldyn.project_state`
    from an arbitrary guess, states interpolated between steps, RATTLE's SHAKE solve) iterate with
    optimistix's `Newton` until converged, in at most `max_steps` iterations. Velocities: the
    mass-weighted projection onto `DPhi(x) xd = 0` (one small linear solve). Both projections are
    differentiable.

    **Arguments:**

    - `atol`: tolerance on `|Phi(x) - Phi(x0)|` (and on the Newton update). It is never taken tighter
      than the rounding of the state's dtype (64 ulps of the constraint values and positions), so the
      default suits float64 and float32 alike.
    - `rtol`: relative tolerance on the Newton update (likewise at least 64 ulps).
    - `max_steps`: the most Newton iterations of a projection iterated until converged.
    - `iterations`: the Newton iterations of the correction after every step (convergence is
      quadratic: a drift `e`, relative to the constraint scale, leaves about `e^4` after two).

    !!! example

        ```python
        traj = cldyn.simulate(system, x0, xd0, ts, solver=cldyn.RK4(), dt0=0.01,
                              stabilisation=cldyn.Projection(atol=1e-10))
        ```
    """

    atol: float = eqx.field(static=True, default=1e-12)
    rtol: float = eqx.field(static=True, default=1e-10)
    max_steps: int = eqx.field(static=True, default=8)
    iterations: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if not (self.atol > 0 and self.rtol >= 0 and self.max_steps >= 1 and self.iterations >= 1):
            raise ValueError("Projection needs atol > 0, rtol >= 0, max_steps >= 1 and iterations >= 1")

    def feedback(self, term, x, xd) -> None:
        del term, x, xd
        return None

    def _newton(self, term: "DynamicsTerm", x: Vector) -> tuple[optx.Newton, Array]:
        """optimistix's Newton with the tolerances (never below the rounding of `x`'s dtype), and
        the absolute tolerance on the residual."""
        eps = jnp.finfo(x.dtype).eps
        scale = jnp.maximum(jnp.max(jnp.abs(term.reference), initial=1.0), jnp.max(jnp.abs(x)))
        atol = jnp.maximum(self.atol, ROUNDOFF_ULPS * eps * scale)
        newton = optx.Newton(
            rtol=max(self.rtol, ROUNDOFF_ULPS * float(eps)), atol=atol, linear_solver=SmallDense()
        )
        return newton, atol

    def positions(
        self, term: "DynamicsTerm", x: Vector, directions: Float[Array, "k n"]
    ) -> tuple[Vector, dfx.RESULTS]:
        """The point `x + directions @ lambda` on the manifold (`term.residual = 0`), by Newton's method
        on `lambda` iterated until converged (at most `max_steps` iterations), and the solve's result.

        With `directions = M^-1 DPhi(x)^T` this is the mass-weighted projection of `x`; `RATTLE` uses
        the directions at the start of its step (SHAKE).
        """
        newton, _ = self._newton(term, x)
        lam0 = jnp.zeros(term.system.num_constraints, dtype=x.dtype)
        solution = optx.root_find(
            lambda lam, _: term.residual(x + directions @ lam),
            newton,
            lam0,
            max_steps=self.max_steps,
            throw=False,
        )
        return x + directions @ solution.value, dfx.RESULTS.promote(solution.result)

    def correct(self, term, x, xd):
        if term.system.num_constraints == 0:
            return x, xd, dfx.RESULTS.successful
        x, result = self.positions(term, x, term.mass_solve(term.jacobian(x).T))
        return x, term.tangent(x, xd), result

    def correct_step(self, term, x, xd):
        if term.system.num_constraints == 0:
            return x, xd, dfx.RESULTS.successful
        jac = term.jacobian(x)
        directions = term.mass_solve(jac.T)
        _, atol = self._newton(term, x)
        # Newton's iterations on lambda, unrolled. Driving optimistix's `Newton.step` here instead
        # costs 40% more per simulated step (batched acrobot, CPU): its step linearises the residual
        # and measures the update, which a fixed number of iterations does not need. The first
        # iteration starts at lambda = 0, that is at x, whose Jacobian is already at hand.
        lam = -small_solve(small_matmul(jac, directions), term.residual(x))
        for _ in range(1, self.iterations):
            y = x + small_matmul(directions, lam)
            lam = lam - small_solve(small_matmul(term.jacobian(y), directions), term.residual(y))
        x = x + small_matmul(directions, lam)
        converged = jnp.max(jnp.abs(term.residual(x)), initial=0.0) <= atol
        result = dfx.RESULTS.where(converged, dfx.RESULTS.successful, dfx.RESULTS.nonlinear_max_steps_reached)
        return x, term.tangent(x, xd), result

    def wrap(self, solver: dfx.AbstractSolver) -> dfx.AbstractSolver:
        from ._solver.projected import ProjectedSolver

        return ProjectedSolver(solver, self)


class Baumgarte(AbstractStabilisation):
    """Baumgarte stabilisation: `Phi'' + 2 alpha Phi' + beta^2 (Phi - Phi0) = 0` instead of `Phi'' = 0`.

    Cheap (no extra solve), but it only damps the drift; it does not remove it, and too large gains
    make the equations stiff. It acts in the vector field, so `RATTLE`, which integrates eq. 6 on the
    manifold where the feedback vanishes, is unaffected by it.

    **Arguments:**

    - `alpha`: damping of the constraint velocity (1/s).
    - `beta`: stiffness of the constraint position (1/s).

    !!! example

        ```python
        traj = cldyn.simulate(system, x0, xd0, ts, stabilisation=cldyn.Baumgarte(10.0, 10.0))
        ```
    """

    alpha: float = eqx.field(static=True)
    beta: float = eqx.field(static=True)

    def __check_init__(self):
        if not (self.alpha >= 0 and self.beta >= 0):
            raise ValueError(f"Baumgarte gains must be non-negative, got {self.alpha}, {self.beta}")

    def feedback(self, term, x, xd):
        if term.system.num_constraints == 0:
            return None
        return -2 * self.alpha * term.rate(x, xd) - self.beta**2 * term.residual(x)

    def correct(self, term, x, xd):
        del term
        return x, xd, dfx.RESULTS.successful

    def correct_step(self, term, x, xd):
        return self.correct(term, x, xd)

    def wrap(self, solver: dfx.AbstractSolver) -> dfx.AbstractSolver:
        return solver
