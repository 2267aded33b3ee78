"""`RK4`: the classical fourth-order Runge-Kutta method, for fixed steps."""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import numpy as np

_RK4_TABLEAU = dfx.ButcherTableau(
    c=np.array([0.5, 0.5, 1.0]),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
)


class RK4(dfx.AbstractERK):
    """The classical fourth-order Runge-Kutta method, for fixed steps.

    The same scheme as MuJoCo's `RK4` integrator, so that the two can be compared step for step. It
    has no embedded error estimate (its `error_order` is `None`), so it always takes fixed steps; use
    `diffrax.Tsit5` or `diffrax.Dopri8` for adaptive steps.

    !!! example

        ```python
        traj = cldyn.simulate(system, x0, xd0, jnp.linspace(0, 10, 1001), solver=cldyn.RK4(), dt0=0.01)
        ```
    """

    tableau: ClassVar[dfx.ButcherTableau] = _RK4_TABLEAU
    interpolation_cls: ClassVar[Callable[..., dfx.AbstractLocalInterpolation]] = (
        dfx.ThirdOrderHermitePolynomialInterpolation.from_k
    )

    def order(self, terms):
        del terms
        return 4

    def error_order(self, terms):
        # a zero "error estimate" must not drive a step-size controller
        del terms
        return None
