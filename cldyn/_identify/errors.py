"""The errors before and after: weak-form accelerations and rollouts on the held-out runs."""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._evaluate import rollout
from .._system import ConstrainedLagrangian
from .result import Errors
from .smoothing import Prepared, TestFunctions


@eqx.filter_jit
def _accelerations(model, x, xd, u):
    return jax.vmap(jax.vmap(model.acceleration))(x, xd, u)


def _run(model, x0, xd0, us, dt):
    # forward mode: the initial-state fit differentiates through this with Jacobian-vector products
    return rollout(model, x0, xd0, us, dt, adjoint=dfx.ForwardMode()).x


@eqx.filter_jit
def _rollout_batch(model, x0, xd0, us, dt: float, measured, window: int):
    """Rollouts from the start of each run, and whether each initial-state fit converged.

    The initial state is estimated with the model itself: starting from the smoothed state, the
    positions and velocities are adjusted (Gauss-Newton) so that the first `window` samples of
    the rollout match the measurement. This removes most of the measurement noise from the initial
    velocity, which otherwise dominates the rollout error of noisy data, for every model alike.
    """

    def one(x0, xd0, us, measured):
        def residual(delta, _):
            xs = _run(model, x0 + delta[0], xd0 + delta[1], us[: window + 1], dt)
            return (xs - measured[: window + 1]).reshape(-1)

        zero = (jnp.zeros_like(x0), jnp.zeros_like(xd0))
        # velocity changes across the constraints are projected away: a rank-deficient problem
        solver = optx.GaussNewton(rtol=1e-6, atol=1e-9, linear_solver=lx.SVD(rcond=1e-8))
        solution = optx.least_squares(residual, solver, zero, max_steps=20, throw=False)
        delta = solution.value
        converged = solution.result == optx.RESULTS.successful
        return _run(model, x0 + delta[0], xd0 + delta[1], us, dt), converged

    # one run after another: batching the Gauss-Newton fit and the projections through their custom
    # derivatives costs more tracing and compilation than the rollouts of a few dozen runs take
    return jax.lax.map(lambda args: one(*args), (x0, xd0, us, measured))


def rollout_errors(
    model: ConstrainedLagrangian, data: Prepared, horizon: float, window: float = 0.2
) -> tuple[np.ndarray, np.ndarray, int]:
    """Keypoint position error over time of rollouts from the first interior state of every run.

    **Returns:** `(ts, error (runs, T, keypoints), number of unconverged initial-state fits)`.
    """
    steps = min(int(round(horizon / data.dt)), data.x.shape[1] - 1)
    ts = np.arange(steps + 1) * data.dt
    start = data.margin
    us = data.u_raw[:, start : start + steps + 1]
    measured = data.x_raw[:, start : start + steps + 1]
    samples = max(2, min(steps, int(round(window / data.dt))))
    xs, converged = _rollout_batch(
        model,
        jnp.asarray(data.x[:, 0]),
        jnp.asarray(data.xd[:, 0]),
        jnp.asarray(us),
        data.dt,
        jnp.asarray(measured),
        samples,
    )
    error = np.linalg.norm((np.asarray(xs) - measured).reshape(xs.shape[0], steps + 1, -1, 2), axis=-1)
    return ts, error, int(np.sum(~np.asarray(converged)))


def errors(
    model: ConstrainedLagrangian, data: Prepared, horizon: float, tests: TestFunctions
) -> tuple[Errors, np.ndarray, np.ndarray]:
    """The model's `Errors` on `data`, with the rollout error over time.

    **Returns:** `(errors, ts, error (runs, T, keypoints))`.
    """
    acc = np.asarray(_accelerations(model, jnp.asarray(data.x), jnp.asarray(data.xd), jnp.asarray(data.u)))
    # the acceleration error averaged over each test function, int psi (xdd_model - xdd) dt, with
    # int psi xdd dt = -int psi' xd dt: no second differences of the measurement
    error = np.einsum("nt,rtk->rnk", tests.psi, acc) + np.einsum("nt,rtk->rnk", tests.dpsi, data.xd)
    accel_rmse = float(np.sqrt(np.mean(error**2)))
    ts, error, unconverged = rollout_errors(model, data, horizon)
    rollout_rmse = float(np.sqrt(np.mean(error**2)))
    return Errors(accel_rmse, rollout_rmse, float(ts[-1]), unconverged), ts, error
