"""`ProjectedSolver`: any diffrax solver, with every step corrected by a stabilisation."""

from typing import TYPE_CHECKING

import diffrax as dfx
import equinox as eqx

from .term import replace_term, unwrap_term

if TYPE_CHECKING:
    from .._stabilisation import AbstractStabilisation


class _AbstractForwardingSolver(dfx.AbstractWrappedSolver):
    """A diffrax solver around another, forwarding everything but `step`."""

    solver: eqx.AbstractVar[dfx.AbstractSolver]
    # diffrax's adjoints set `scan_kind` on Runge-Kutta solvers (for forward-mode autodiff), and
    # isinstance checks see through a wrapper: it receives the setting and passes it on
    scan_kind: eqx.AbstractVar[str | None]

    def _inner(self) -> dfx.AbstractSolver:
        if self.scan_kind is None or getattr(self.solver, "scan_kind", True) is not None:
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

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


class ProjectedSolver(_AbstractForwardingSolver):
    """Wraps a diffrax solver so that every step ends on the constraint manifold.

    After each step of `solver`, the state is corrected by `projection.correct_step` (for `Projection`:
    positions onto `Phi(x) = reference`, velocities onto `DPhi(x) xd = 0`), and the step's result
    reports a correction that failed. The terms must be a `DynamicsTerm`. This is what
    `Projection().wrap(solver)` returns and what `simulate` integrates with by default.

    **Arguments:**

    - `solver`: any diffrax ODE solver.
    - `projection`: the correction, usually a `cldyn.Projection` (any `AbstractStabilisation`: one
      that corrects nothing leaves the steps as they are).
    - `hold_controls`: apply the control of every step as `AbstractControl.over_step` gives it: a
      `ZeroOrderHold` then holds one sample over the whole step, as MuJoCo does, instead of reading
      the next sample at the step's last stage. `simulate` sets it when the control jumps.

    !!! example

        ```python
        term = cldyn.DynamicsTerm(system, system.constraint(x0))
        solver = cldyn.ProjectedSolver(cldyn.RK4(), cldyn.Projection())
        solution = diffrax.diffeqsolve(term, solver, 0.0, 10.0, 0.01, (x0, xd0))
        ```
    """

    solver: dfx.AbstractSolver
    projection: "AbstractStabilisation"
    hold_controls: bool = eqx.field(default=False, static=True)
    scan_kind: str | None = None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        if self.hold_controls:
            term, direction = unwrap_term(terms)
            if term.control is not None:
                # the solver sees times multiplied by the direction of integration
                held = term.control.over_step(direction * t0, direction * t1)
                terms = replace_term(terms, eqx.tree_at(lambda s: s.control, term, held))
        y1, error, dense_info, solver_state, result = self._inner().step(
            terms, t0, t1, y0, args, solver_state, made_jump
        )
        x1, xd1, corrected = self.projection.correct_step(unwrap_term(terms)[0], *y1)
        y1 = (x1, xd1)
        # the interpolant ends at the corrected state, so saved step ends lie on the manifold
        dense_info = dict(dense_info, y1=y1)
        # diffrax stops at the first accepted step whose result is unsuccessful (fixed-step controllers
        # accept every step), so a failed correction ends the solve with its result
        result = dfx.RESULTS.where(result == dfx.RESULTS.successful, corrected, result)
        return y1, error, dense_info, solver_state, result

