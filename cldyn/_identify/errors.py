"""The errors before and after: weak-form accelerations and rollouts on the held-out runs."""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._control import ConstantControl
from .._coordinates import AbstractCoordinate, JointMap
from .._data import Sequences
from .._integrate import project_state
from .._solver import DynamicsTerm
from .._stabilisation import Projection
from .._system import ConstrainedLagrangian
from .result import Errors
from .smoothing import Prepared, Smoothing, TestFunctions, prepare


@eqx.filter_jit
def _accelerations(model, x, xd, u):
    return jax.vmap(jax.vmap(model.acceleration))(x, xd, u)


# RK4's stages as a loop: y1 = y0 + dt * sum_i b_i k_i, k_i = f(y0 + dt * a_i k_(i-1))
_RK4_STAGES = np.array([[0.0, 1 / 6], [0.5, 1 / 3], [0.5, 1 / 3], [1.0, 1 / 6]])


def _step_rollout(model: ConstrainedLagrangian, x0, xd0, controls, dt: float):
    """The positions of `cldyn.rollout(model, x0, xd0, controls, dt, throw=False)`, `(T, k)`: the
    initial state projected onto the constraint manifold, then one RK4 step per sample with that
    sample's control held over it, each step's end projected (`Projection`); after a step whose
    projection fails, the positions are infinite (`rollout` stops there and leaves them so).

    The same scheme and the same pieces (`DynamicsTerm`, `Projection.correct_step`), as a scan over
    the samples whose step loops over RK4's four stages: one copy of the model's acceleration to
    compile instead of four, and none of the general solver's machinery. identify compiles a rollout
    for every trial model and runs each only briefly, so compiling is most of its cost: a new model's
    fit of the initial states takes a third to a half of the time it took with `cldyn.rollout`
    (`benchmarks/identify_compile.py`, CPU: pendulum 2.5 -> 0.9 s, acrobot 3.2 -> 1.3 s).
    """
    x0, xd0, _ = project_state(model, x0, xd0, throw=False)
    projection = Projection()
    reference = model.constraint(x0)
    stages = jnp.asarray(_RK4_STAGES, dtype=x0.dtype)
    k = x0.shape[0]

    def step(carry, u):
        x, xd, failed = carry
        term = DynamicsTerm(model, reference, control=ConstantControl(u), stabilisation=projection)
        y0 = jnp.concatenate([x, xd])

        def stage(inner, coefficients):
            total, slope = inner
            y = y0 + coefficients[0] * dt * slope
            slope = jnp.concatenate(term.vf(0.0, (y[:k], y[k:]), None))
            return (total + coefficients[1] * slope, slope), None

        (total, _), _ = jax.lax.scan(stage, (jnp.zeros_like(y0), jnp.zeros_like(y0)), stages)
        y1 = y0 + dt * total
        x, xd, result = projection.correct_step(term, y1[:k], y1[k:])
        # as diffrax stops: the step whose projection fails is kept, those after it are not taken
        saved = jnp.where(failed, jnp.inf, x)
        return (x, xd, failed | (result != dfx.RESULTS.successful)), saved

    _, xs = jax.lax.scan(step, (x0, xd0, jnp.asarray(False)), controls[:-1])
    return jnp.concatenate([x0[None], xs])


def _rollout_states(model: ConstrainedLagrangian, states, controls, dt: float):
    """`_step_rollout` from each of the states `(B, 2k)` (positions, then velocities) with its
    controls `(B, T, l)`: the positions `(B, T, k)`. As one batch: the scan batches at about the
    compile time of one rollout after another (`lax.map`) and runs 5-10 times faster (acrobot, 12
    runs: 0.02 s a call against 0.2 s)."""
    k = states.shape[1] // 2
    return jax.vmap(lambda y, u: _step_rollout(model, y[:k], y[k:], u, dt))(states, controls)


@eqx.filter_jit
def _rollout_batch(
    model,
    x0,
    xd0,
    us,
    dt: float,
    measured,
    window: int,
    valid,
    *,
    max_steps: int = 20,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    roll=_rollout_states,
    substeps: int = 1,
):
    """Rollouts from the start of each run, and whether each initial-state fit converged.

    Each interval `dt` of the data is integrated in `substeps` steps, its control held over them: a
    step must resolve the motion, whatever the rate at which it was sampled.

    The initial state is estimated with the model itself: starting from the smoothed state, the
    positions and velocities are adjusted (Gauss-Newton) so that the first `window` samples of
    the rollout match the measurement (those of them that are `valid`, `(runs, window + 1)`: a run
    that starts at a joint limit is not fitted). This removes most of the measurement noise from the
    initial velocity, which otherwise dominates the rollout error of noisy data, for every model alike.

    The Gauss-Newton Jacobian is taken by forward differences: every iteration rolls out each run
    and its `2k` perturbed initial states as one batch of plain (undifferentiated) rollouts
    (`_step_rollout`, `cldyn.rollout`'s scheme), and the unperturbed rollout of the last iteration
    is the result. One rollout loop to trace and compile, a fraction of what differentiating through
    it costs; the minimiser is the same. (`roll(model, states (B, 2k), controls (B, T, l), dt)`,
    the positions `(B, T, k)`, replaces that batch for `benchmarks/identify_compile.py`'s
    reference.)
    Velocity changes across the constraints are projected away by the rollout, so the
    least-squares problem is rank-deficient: the steps are minimum-norm (SVD). A run whose rollouts
    turn non-finite (a model that cannot follow it, say) stops where it is, unconverged; its rollout
    may then be non-finite, which the caller counts as a divergence.
    """
    runs, k = x0.shape
    n = 2 * k
    start = jnp.concatenate([x0, xd0], axis=1)  # (runs, 2k)
    # between the truncation error of the differences and the projection's Newton tolerance
    relative_step = jnp.cbrt(jnp.finfo(start.dtype).eps)
    target = measured[:, : window + 1].reshape(runs, -1)
    # per residual row, sample by sample as `target` lays them out
    weight = jnp.repeat(valid[:, : window + 1].astype(measured.dtype), measured.shape[-1], axis=1)
    probe_us = jnp.repeat(us, n + 1, axis=0)
    if substeps > 1:
        probe_us = jnp.repeat(probe_us, substeps, axis=1)[:, : (us.shape[1] - 1) * substeps + 1]

    def cond(carry):
        _, count, done, _, _ = carry
        return (count < max_steps) & ~jnp.all(done)

    def body(carry):
        y, count, done, converged, _ = carry
        h = relative_step * (1 + jnp.abs(y))  # (runs, 2k)
        probes = y[:, None, :] + jnp.concatenate([jnp.zeros((runs, 1, n), y.dtype), jax.vmap(jnp.diag)(h)], 1)
        xs = roll(model, probes.reshape(-1, n), probe_us, dt / substeps)[:, ::substeps]
        xs = xs.reshape((runs, n + 1) + measured.shape[1:])
        window_xs = xs[:, :, : window + 1].reshape(runs, n + 1, -1)
        jac = jnp.swapaxes((window_xs[:, 1:] - window_xs[:, :1]) / h[:, :, None], 1, 2) * weight[:, :, None]
        delta = jax.vmap(lambda a, b: jnp.linalg.lstsq(a, b, rcond=1e-6)[0])(
            jac, (window_xs[:, 0] - target) * weight
        )
        small = jnp.linalg.norm(delta, axis=1) <= atol + rtol * jnp.linalg.norm(y, axis=1)
        failed = ~jnp.all(jnp.isfinite(delta), axis=1)
        # a converged run keeps the state its rollout came from; so does a failed one, and every run
        # on the last pass
        keep = done | small | failed | (count + 1 >= max_steps)
        converged = converged | (small & ~done)
        return jnp.where(keep[:, None], y, y - delta), count + 1, done | small | failed, converged, xs[:, 0]

    empty = jnp.zeros((runs,) + measured.shape[1:], measured.dtype)
    none = jnp.zeros(runs, bool)
    _, _, _, converged, xs = jax.lax.while_loop(cond, body, (start, 0, none, none, empty))
    return xs, converged


def rollout_errors(
    model: ConstrainedLagrangian, data: Prepared, horizon: float, window: float = 0.2, substeps: int = 1
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Keypoint position error over time of rollouts from the first kept state of every run, with the
    controls held between kept samples (`data.u_hold`), each interval integrated in `substeps` steps.
    A run's error ends before its first excluded sample (a joint at its limit, which the model does not
    know): NaN from there on. A rollout that turns non-finite before that has an infinite error.

    **Returns:** `(ts, error (runs, T, keypoints), unconverged initial-state fits, diverged rollouts)`.
    """
    steps = min(int(round(horizon / data.dt)), data.x.shape[1] - 1)
    ts = np.arange(steps + 1) * data.dt
    us = data.u_hold[:, : steps + 1]
    measured = data.x_measured[:, : steps + 1]
    samples = max(2, min(steps, int(round(window / data.dt))))
    reached = np.cumsum(data.excluded[:, : steps + 1], axis=1) > 0
    xs, converged = _rollout_batch(
        model,
        jnp.asarray(data.x[:, 0]),
        jnp.asarray(data.xd[:, 0]),
        jnp.asarray(us),
        data.dt,
        jnp.asarray(measured),
        samples,
        jnp.asarray(~reached),
        substeps=substeps,
    )
    error = np.linalg.norm((np.asarray(xs) - measured).reshape(xs.shape[0], steps + 1, -1, 2), axis=-1)
    error = np.where(np.isfinite(error), error, np.inf)
    error = np.where(reached[..., None], np.nan, error)
    diverged = int(np.sum(np.any(np.isinf(error), axis=(1, 2))))
    unconverged = int(np.sum(~np.asarray(converged) & ~reached[:, 0]))
    return ts, error, unconverged, diverged


def errors(
    model: ConstrainedLagrangian,
    data: Prepared,
    horizon: float,
    tests: TestFunctions,
    kept: np.ndarray | None = None,
    substeps: int = 1,
) -> tuple[Errors, np.ndarray, np.ndarray]:
    """The model's `Errors` on `data`, with the rollout error over time; `kept` `(runs, n)` says which
    test functions count for the acceleration error (all by default); `substeps` integration steps per
    interval of the data.

    **Returns:** `(errors, ts, error (runs, T, keypoints))`.
    """
    acc = np.asarray(_accelerations(model, jnp.asarray(data.x), jnp.asarray(data.xd), jnp.asarray(data.u)))
    # the acceleration error averaged over each test function, int psi (xdd_model - xdd) dt, with
    # int psi xdd dt = -int psi' xd dt: no second differences of the measurement
    error = np.einsum("nt,rtk->rnk", tests.psi, acc) + np.einsum("nt,rtk->rnk", tests.dpsi, data.xd)
    if kept is None:
        kept = np.ones(error.shape[:2], dtype=bool)
    accel_rmse = float(np.sqrt(np.sum(error[kept] ** 2) / max(error[kept].size, 1)))
    ts, error, unconverged, diverged = rollout_errors(model, data, horizon, substeps=substeps)
    return Errors(accel_rmse, _rmse(error), float(ts[-1]), unconverged, diverged), ts, error


def _rmse(error: np.ndarray) -> float:
    """The RMS of a rollout error over its valid (not NaN) entries: infinite for a diverged rollout,
    NaN where no entry is valid."""
    valid = ~np.isnan(error)
    return float(np.sqrt(np.mean(error[valid] ** 2))) if valid.any() else float("nan")


def held_out_rollout_rmse(
    models: list[ConstrainedLagrangian],
    data: Sequences,
    runs,
    *,
    coordinates: tuple[AbstractCoordinate, ...],
    joints: JointMap | None = None,
    smoothing: Smoothing = Smoothing(),
    horizon: float = 1.0,
) -> list[float]:
    """`identify`'s held-out rollout error (`Errors.rollout_rmse_1s`) of each of `models` on the runs
    `runs` of `data`, smoothed and integrated as `identify` does with the same arguments: for a change
    made to a model beside `identify` (the energy balance's damping, say) to pass `identify`'s test."""
    x = np.asarray(data.x, dtype=float)
    choice = smoothing.choose(x, data.dt)  # from every run, as identify chooses it
    runs = np.asarray(runs)  # each run is smoothed on its own: only the held-out ones are needed
    held = prepare(x[runs], np.asarray(data.u, dtype=float)[runs], choice, tuple(coordinates), joints)
    return [_rmse(rollout_errors(m, held, horizon, substeps=choice.substeps)[1]) for m in models]
