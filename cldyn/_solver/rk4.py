"""`RK4`: the classical fourth-order Runge-Kutta method, for fixed steps."""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import jax.numpy as jnp
import jax.tree_util as jtu
from equinox.internal import ω


class RK4(dfx.AbstractSolver):
    """The classical fourth-order Runge-Kutta method, for fixed steps.

    $k_1 = f(t_0, y_0)$, $k_2 = f(t_0 + h/2, y_0 + h k_1/2)$, $k_3 = f(t_0 + h/2, y_0 + h k_2/2)$,
    $k_4 = f(t_0 + h, y_0 + h k_3)$, $y_1 = y_0 + h (k_1 + 2 k_2 + 2 k_3 + k_4) / 6$: the same scheme
    as MuJoCo's `RK4` integrator, so that the two can be compared step for step. It has no error
    estimate, so it always takes fixed steps; use `diffrax.Tsit5` or `diffrax.Dopri8` for adaptive
    steps. Dense output is the cubic Hermite interpolant of diffrax's `RK4`.

    The four stages are written out in one step rather than looped over a Butcher tableau (as
    diffrax's explicit Runge-Kutta solvers do, for their variable stage counts and reverse-mode
    memory): XLA then fuses the step of a small mechanical system into a few kernels, about half
    the time per step of a tableau loop on CPU.

    !!! example

        ```python
        traj = cldyn.simulate(system, x0, xd0, jnp.linspace(0, 10, 1001), solver=cldyn.RK4(), dt0=0.01)
        ```
    """

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., dfx.AbstractLocalInterpolation]] = (
        dfx.ThirdOrderHermitePolynomialInterpolation.from_k
    )

    def order(self, terms):
        del terms
        return 4

    def init(self, terms, t0, t1, y0, args):
        del terms, t0, t1, y0, args
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        control = terms.contr(t0, t1)
        half = t0 + 0.5 * (t1 - t0)
        k1 = terms.vf_prod(t0, y0, args, control)
        k2 = terms.vf_prod(half, (y0**ω + 0.5 * k1**ω).ω, args, control)
        k3 = terms.vf_prod(half, (y0**ω + 0.5 * k2**ω).ω, args, control)
        k4 = terms.vf_prod(t1, (y0**ω + k3**ω).ω, args, control)
        y1 = (y0**ω + (k1**ω + 2 * k2**ω + 2 * k3**ω + k4**ω) / 6).ω
        # the Hermite interpolant takes the first and the last stage as the end slopes
        k = jtu.tree_map(lambda first, last: jnp.stack([first, last]), k1, k4)
        return y1, None, dict(y0=y0, y1=y1, k=k), None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
