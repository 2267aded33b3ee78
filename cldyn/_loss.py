"""Training losses on runs of keypoint states: collocation (KeyCLD eq. 11-13), rollouts, inverse dynamics.

The losses take a batch of `Sequences` (positions `(runs, T, k)`, controls, the interval `h`), so the
same code serves state data (from MuJoCo or an analytic model) and keypoints that come out of an
image encoder. Every loss has the signature `loss(model, batch) -> scalar` and works for any
`AbstractDynamics`: the constrained Lagrangian of KeyCLD, its variant without constraints, and the
neural ODE baseline. Rollouts go through `cldyn.rollout`, the one held-control rollout.
"""

import abc

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree

from ._custom_types import Scalar
from ._data import Sequences, central_difference
from ._evaluate import rollout
from ._integrate import project_state
from ._solver import RK4
from ._stabilisation import AbstractStabilisation
from ._system import AbstractDynamics


def _per_state(fn, *arrays):
    """`fn` mapped over the leading (runs, time) axes of every array."""
    return jax.vmap(jax.vmap(fn))(*arrays)


def _project_velocities(model, x, xd):
    """Velocities projected onto `DPhi(x) xd = 0` (mass-weighted) for constrained models; unchanged
    for models without constraints."""
    if model.num_constraints == 0:
        return xd
    return _per_state(lambda a, b: project_state(model, a, b)[1], x, xd)


def _check_samples(name: str, batch: Sequences, needed: int) -> None:
    if batch.num_samples < needed:
        raise ValueError(f"{name} needs runs of at least {needed} samples, got {batch.num_samples}")


def _check_model(name: str, model, batch: Sequences) -> None:
    if not isinstance(model, AbstractDynamics):
        raise TypeError(f"{name}: the model must be an AbstractDynamics, got {type(model).__name__}")
    if model.size != batch.size or model.num_inputs != batch.num_inputs:
        raise ValueError(
            f"{name}: the model has k={model.size}, l={model.num_inputs} but the data k={batch.size}, "
            f"l={batch.num_inputs}"
        )


def _squared_norm(residual):
    return jnp.mean(jnp.sum(residual**2, axis=-1))


class AbstractLoss(eqx.Module):
    """A training loss `loss(model, batch) -> scalar` over a batch of `Sequences`.

    Losses add up and scale: `Collocation() + 0.1 * Rollout()` is a `LossSum`. The losses here take
    an `AbstractDynamics` and `Sequences`; other packages' losses take other models and batches
    (keyvision's take a model of images and batches of frames) and combine the same way.
    """

    @abc.abstractmethod
    def __call__(self, model: PyTree, batch: PyTree) -> Scalar:
        """The loss of `model` on `batch`, a scalar."""

    def __add__(self, other: "AbstractLoss") -> "LossSum":
        if not isinstance(other, AbstractLoss):
            return NotImplemented
        return LossSum(_terms(self) + _terms(other))

    def __rmul__(self, weight: float | int) -> "LossSum":
        if not isinstance(weight, int | float):
            return NotImplemented
        return LossSum(tuple((float(weight) * w, loss) for w, loss in _terms(self)))

    __mul__ = __rmul__


def _terms(loss: AbstractLoss) -> tuple[tuple[float, AbstractLoss], ...]:
    return loss.terms if isinstance(loss, LossSum) else ((1.0, loss),)


class LossSum(AbstractLoss):
    """A weighted sum of losses, $\\sum_j w_j L_j$; what `+` and `*` on losses build.

    **Arguments:**

    - `terms`: pairs `(weight, loss)`.

    !!! example

        ```python
        loss = cldyn.Collocation() + 0.1 * cldyn.Rollout(steps=4)   # a LossSum of two terms
        ```
    """

    terms: tuple[tuple[float, AbstractLoss], ...] = eqx.field(static=True)

    def __check_init__(self):
        for weight, loss in self.terms:
            if not isinstance(loss, AbstractLoss) or not np.isfinite(weight):
                raise ValueError(f"LossSum takes (finite weight, loss) pairs, got ({weight}, {loss})")

    def __call__(self, model: PyTree, batch: PyTree) -> Scalar:
        return sum(weight * loss(model, batch) for weight, loss in self.terms)


class Collocation(AbstractLoss):
    """The finite-difference collocation loss of KeyCLD (eq. 11-13).

    Velocities and accelerations are estimated by central differences,
    $\\hat{\\dot x}_i = (x_{i+1} - x_{i-1}) / 2h$ (eq. 11) and
    $\\hat{\\ddot x}_i = (\\hat{\\dot x}_{i+1} - \\hat{\\dot x}_{i-1}) / 2h$ (eq. 12), and the loss is
    $L_d = \\operatorname{mean}_i \\| \\hat{\\ddot x}_i - \\ddot x(x_i, \\hat{\\dot x}_i, u_i) \\|^2$ over
    samples `2 .. T-3` of every run (eq. 13, averaged rather than summed). No ODE solver is involved,
    and the estimates are second-order accurate: on an exact trajectory the loss is `O(h^4)`.

    With `order=4` the same five samples `x_{i-2} .. x_{i+2}` give fourth-order estimates instead,
    $\\hat{\\dot x}_i = (x_{i-2} - 8 x_{i-1} + 8 x_{i+1} - x_{i+2}) / 12h$ and
    $\\hat{\\ddot x}_i = (-x_{i-2} + 16 x_{i-1} - 30 x_i + 16 x_{i+1} - x_{i+2}) / 12h^2$: a much smaller
    bias on smooth, noise-free states (the loss is `O(h^8)` on an exact trajectory), at the price of
    amplifying position noise about five times more than eq. 12.

    **Arguments:**

    - `project`: project the estimated velocities onto the constraint tangent space
      `DPhi(x) xd = 0` (mass-weighted, as `cldyn.project_state`) before evaluating the model; only
      for constrained models.
    - `order`: 2 for the paper's central differences (eq. 11-12), 4 for the fourth-order stencils.

    !!! example

        ```python
        loss = cldyn.Collocation()
        value = loss(model, data)   # data: cldyn.Sequences, runs of at least 5 samples
        ```
    """

    project: bool = eqx.field(static=True, default=False)
    order: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if self.order not in (2, 4):
            raise ValueError(f"Collocation order must be 2 or 4, got {self.order}")

    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
        _check_samples("Collocation", batch, 5)
        _check_model("Collocation", model, batch)
        h, x = batch.dt, batch.x
        if self.order == 2:
            xd = central_difference(x, h)
            xdd = central_difference(xd, h)
            xd = xd[:, 1:-1]
        else:
            a, b, c, d, e = x[:, :-4], x[:, 1:-3], x[:, 2:-2], x[:, 3:-1], x[:, 4:]
            xd = (a - 8 * b + 8 * d - e) / (12 * h)
            xdd = (-a + 16 * b - 30 * c + 16 * d - e) / (12 * h**2)
        x, u = x[:, 2:-2], batch.u[:, 2:-2]
        if self.project:
            xd = _project_velocities(model, x, xd)
        predicted = _per_state(model.acceleration, x, xd, u)
        return _squared_norm(xdd - predicted)


def _rollouts(model, x0, xd0, controls, h, *, solver, stabilisation, dt0=None):
    """Positions after the first sample of `cldyn.rollout` from every start `(runs, starts, ...)`."""

    def one(a, b, c):
        run = rollout(model, a, b, c, h, solver=solver, stabilisation=stabilisation, dt0=dt0)
        return run.x[1:]

    return _per_state(one, x0, xd0, controls)


class Rollout(AbstractLoss):
    """A multi-step rollout loss: from every state, predict the next `steps` positions.

    Each sample `i` with a central-difference velocity $\\hat{\\dot x}_i$ (eq. 11) starts a rollout of
    `steps` steps of `h` (`cldyn.rollout`, the controls of the samples it crosses held in turn); the
    loss is the mean squared position error over all starts and steps, divided by `h^4` so that, like
    `Collocation`, it is in units of acceleration squared. By default the rollout takes explicit
    Euler steps, $x_{j+1} = x_j + h \\dot x_j$, $\\dot x_{j+1} = \\dot x_j + h \\ddot x(x_j, \\dot x_j, u_j)$,
    as the KeyCLD authors' code does (4 steps); any diffrax solver can take its place. For
    constrained models the initial velocity is projected onto the constraint tangent space
    (`rollout`'s `project=True`): positions are kept, and a finite-difference velocity that stretches
    a constraint is corrected.

    Explicit Euler is only first-order accurate: on exact data its best fit overestimates
    accelerations by the factor `n^2 / (n (n - 1))` at step `n`. Combine it with `Collocation`, or
    pass a higher-order solver such as `cldyn.RK4()` where the bias matters.

    **Arguments:**

    - `steps`: the number of steps `n` of every rollout.
    - `solver`: a diffrax solver taking fixed steps of `h`; `diffrax.Euler()` by default.
    - `stabilisation`: the constraint stabilisation of the rollout; none by default (rollouts are
      short).

    !!! example

        ```python
        loss = cldyn.Collocation() + cldyn.Rollout(steps=4)
        ```
    """

    steps: int = eqx.field(static=True, default=4)
    solver: dfx.AbstractSolver = dfx.Euler()
    stabilisation: AbstractStabilisation | None = None

    def __check_init__(self):
        if not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"Rollout needs an integer steps >= 1, got {self.steps!r}")

    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
        n, h = self.steps, batch.dt
        _check_samples(f"Rollout(steps={n})", batch, n + 2)
        _check_model("Rollout", model, batch)
        # samples 1 .. T-1-n start a rollout: each has a central difference and n samples after it
        starts = batch.num_samples - 1 - n
        x0 = batch.x[:, 1 : 1 + starts]
        xd0 = central_difference(batch.x, h)[:, :starts]
        # targets[r, i, j] = x[r, 2 + i + j]; controls[r, i, j] = u[r, 1 + i + j] for j = 0 .. n
        offsets = np.arange(starts)[:, None] + np.arange(n + 1)[None, :]
        targets = batch.x[:, 2 + offsets[:, :-1]]
        controls = batch.u[:, 1 + offsets]
        predicted = _rollouts(
            model, x0, xd0, controls, h, solver=self.solver, stabilisation=self.stabilisation
        )
        return jnp.mean(jnp.sum((predicted - targets) ** 2, axis=-1)) / h**4


class MultipleShooting(AbstractLoss):
    """Multiple shooting: every run is cut into segments, each integrated by `cldyn.rollout`.

    Segment `s` starts at sample `1 + s * segment` from the measured position and the
    central-difference velocity (eq. 11; projected onto the constraint tangent space for constrained
    models) and is integrated over `segment` intervals with the run's controls; the loss is the mean
    squared position error over all predicted samples, divided by `h^4` as in `Rollout`. The segment
    starts come from the data rather than being free variables, so segments are independent.

    **Arguments:**

    - `segment`: the number of intervals per segment.
    - `solver`: a diffrax solver; `cldyn.RK4()` (fixed steps) by default.
    - `dt0`: the integration step; the sampling interval by default.
    - `stabilisation`: the constraint stabilisation of the rollouts; none by default.

    !!! example

        ```python
        loss = cldyn.MultipleShooting(segment=10)
        ```
    """

    segment: int = eqx.field(static=True, default=10)
    solver: dfx.AbstractSolver = RK4()
    dt0: float | None = eqx.field(static=True, default=None)
    stabilisation: AbstractStabilisation | None = None

    def __check_init__(self):
        if not isinstance(self.segment, int) or self.segment < 1:
            raise ValueError(f"MultipleShooting needs an integer segment >= 1, got {self.segment!r}")
        if self.dt0 is not None and not (np.isfinite(self.dt0) and self.dt0 > 0):
            raise ValueError(f"MultipleShooting: dt0 must be a positive step, got {self.dt0!r}")

    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
        n, h = self.segment, batch.dt
        _check_samples(f"MultipleShooting(segment={n})", batch, n + 3)
        _check_model("MultipleShooting", model, batch)
        count = (batch.num_samples - 2) // n
        starts = 1 + n * np.arange(count)
        x0 = batch.x[:, starts]
        xd0 = central_difference(batch.x, h)[:, starts - 1]
        window = starts[:, None] + np.arange(n + 1)[None, :]
        targets = batch.x[:, window[:, 1:]]
        controls = batch.u[:, window]
        predicted = _rollouts(
            model,
            x0,
            xd0,
            controls,
            h,
            solver=self.solver,
            stabilisation=self.stabilisation,
            dt0=self.dt0,
        )
        return jnp.mean(jnp.sum((predicted - targets) ** 2, axis=-1)) / h**4


class InverseDynamics(AbstractLoss):
    """The inverse-dynamics loss, when accelerations and controls are measured.

    $L = \\operatorname{mean}_i \\| \\ddot x_i - \\ddot x(x_i, \\dot x_i, u_i) \\|^2$ over every sample,
    with the measured accelerations `batch.xdd` and velocities `batch.xd` (central differences on the
    interior samples when `batch.xd` is absent).

    **Arguments:**

    - `project`: project the velocities onto the constraint tangent space first.

    !!! example

        ```python
        data = cldyn.Sequences(x, u, dt, xd=xd, xdd=xdd)   # e.g. recorded with cldyn.mujoco.record
        value = cldyn.InverseDynamics()(model, data)
        ```
    """

    project: bool = eqx.field(static=True, default=False)

    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
        if batch.xdd is None:
            raise ValueError("InverseDynamics needs measured accelerations: Sequences(..., xdd=...)")
        _check_model("InverseDynamics", model, batch)
        x, u, xdd = batch.x, batch.u, batch.xdd
        if batch.xd is None:
            _check_samples("InverseDynamics (velocities by central differences)", batch, 3)
            xd = central_difference(x, batch.dt)
            x, u, xdd = x[:, 1:-1], u[:, 1:-1], xdd[:, 1:-1]
        else:
            xd = batch.xd
        if self.project:
            xd = _project_velocities(model, x, xd)
        return _squared_norm(xdd - _per_state(model.acceleration, x, xd, u))
