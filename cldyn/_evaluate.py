"""Evaluation of dynamics on held-out runs: the held-control rollout, valid prediction time,
relative errors.

Metrics act on keypoint trajectories in state space (positions in metres), the counterpart of the
image-space metrics of the KeyCLD paper (eq. 16): a model is rolled out from the first states of a
held-out run and compared with the measured positions.
"""

import dataclasses

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._control import ZeroOrderHold
from ._custom_types import ArrayInput
from ._data import Sequences, central_difference
from ._integrate import Trajectory, simulate
from ._solver import RK4
from ._stabilisation import AbstractStabilisation, Projection
from ._system import AbstractDynamics, ConstrainedLagrangian


def rollout(
    model: AbstractDynamics,
    x0: ArrayInput,
    xd0: ArrayInput,
    controls: ArrayInput,
    dt: float,
    *,
    solver: dfx.AbstractSolver = RK4(),
    stabilisation: AbstractStabilisation | None = Projection(),
    project: bool = True,
    dt0: float | None = None,
    adjoint: dfx.AbstractAdjoint | None = None,
    throw: bool = True,
) -> Trajectory:
    """One run of a model from a state, with sampled controls each held until the next sample.

    How recorded runs are replayed (MuJoCo holds `ctrl` between samples; KeyCLD's data hold one
    action per run): `cldyn.simulate` with `cldyn.ZeroOrderHold(controls, dt)`, saving the state at
    the sample times `dt * arange(T)`. The losses (`Rollout`, `MultipleShooting`) and `evaluate`
    roll out through this function; `identify`'s held-out rollouts integrate the same scheme in a
    loop of its own that compiles faster. One example in, one out: `jax.vmap` it over runs.

    **Arguments:**

    - `model`: any `AbstractDynamics`.
    - `x0`, `xd0`: the initial positions and velocities, shape `(k,)`.
    - `controls`: the control at every sample, shape `(T, l)` with `T >= 2`, applied from its
      sample to the next; `T` sets the number of samples of the run.
    - `dt`: the sampling interval `h`.
    - `solver`: a diffrax solver; `cldyn.RK4()` by default.
    - `stabilisation`: the constraint stabilisation (`Projection()` by default, or `None`).
    - `project`: project the initial state onto the constraint manifold (constrained models only):
      an estimated velocity rarely satisfies `DPhi(x0) xd0 = 0` exactly.
    - `dt0`: the integration step; one step per sample (`dt`) by default. Fixed steps always: an
      adaptive solver takes steps of `dt0` too.
    - `adjoint`: how to differentiate through the solve (a diffrax adjoint); `simulate`'s default
      by default.
    - `throw`: raise when a solver fails (as `diffrax.diffeqsolve`); with `False` the failure is in
      the trajectory's result.

    **Returns:** a `Trajectory` with `ts = dt * arange(T)`, `x`, `xd` (shape `(T, k)`) and `u`.

    !!! example

        ```python
        run = cldyn.rollout(model, data.x[0, 0], xd0, data.u[0], data.dt)
        runs = jax.vmap(lambda a, b, c: cldyn.rollout(model, a, b, c, data.dt))(x0s, xd0s, data.u)
        ```
    """
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"rollout: dt must be a positive sampling interval, got {dt}")
    controls = jnp.asarray(controls)
    if controls.ndim != 2 or controls.shape[0] < 2:
        raise ValueError(
            f"rollout: controls must have shape (T, l) with T >= 2 samples, got {controls.shape}"
        )
    # the save times and controls take the state's precision, so that a float32 model rolls out in
    # float32 whatever JAX's default precision
    x0 = jnp.asarray(x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else jnp.result_type(float)
    ts = (dt * np.arange(controls.shape[0])).astype(dtype)
    if jnp.issubdtype(controls.dtype, jnp.floating):
        controls = controls.astype(dtype)
    options = {} if adjoint is None else {"adjoint": adjoint}
    return simulate(
        model, x0, xd0, ts, control=ZeroOrderHold(controls, dt), solver=solver,
        dt0=dt if dt0 is None else dt0, stabilisation=stabilisation, project=project, throw=throw,
        **options,
    )


def failed_samples(trajectory: Trajectory) -> Array:
    """Which samples of a `rollout(..., throw=False)` lie at or after its failure, `(T,)` booleans.

    On a failure (a projection that did not converge) diffrax stops: it keeps the failing step's
    state, which is off the constraints, and leaves the samples it did not reach infinite. So the
    samples from the first one that is not finite on are failed, and so is the last finite one when
    the result says the solve failed.
    """
    finite = jnp.all(jnp.isfinite(trajectory.x), axis=-1) & jnp.all(jnp.isfinite(trajectory.xd), axis=-1)
    after = jnp.cumsum(~finite) > 0
    last = jnp.sum(~after) - 1  # the last finite sample before the first that is not
    stopped = trajectory.result != dfx.RESULTS.successful
    return after | (stopped & (jnp.arange(finite.shape[0]) == last))


def _pair(predicted, truth) -> tuple[Array, Array]:
    predicted, truth = jnp.asarray(predicted), jnp.asarray(truth)
    if predicted.shape != truth.shape or predicted.ndim < 2:
        raise ValueError(
            "predicted and truth must have the same shape (..., T, k), "
            f"got {predicted.shape} and {truth.shape}"
        )
    return predicted, truth


def keypoint_error(
    predicted: Float[ArrayLike, "*runs T k"], truth: Float[ArrayLike, "*runs T k"], *, dim: int = 2
) -> Float[Array, "*runs T"]:
    """The position error of the worst keypoint at every sample: $\\max_j |p_j - \\hat p_j|$.

    **Arguments:**

    - `predicted`, `truth`: keypoint positions, shape `(..., T, k)` with `k = dim * keypoints`.
    - `dim`: dimension of each keypoint.

    **Returns:** the error in the units of the positions, shape `(..., T)`.
    """
    predicted, truth = _pair(predicted, truth)
    if predicted.shape[-1] % dim:
        raise ValueError(f"k = {predicted.shape[-1]} is not a multiple of dim = {dim}")
    delta = (predicted - truth).reshape(*predicted.shape[:-1], -1, dim)
    return jnp.max(jnp.sqrt(jnp.sum(delta**2, axis=-1)), axis=-1)


def valid_prediction_time(
    predicted: Float[ArrayLike, "*runs T k"],
    truth: Float[ArrayLike, "*runs T k"],
    *,
    threshold: float,
    dt: float | None = None,
    dim: int = 2,
) -> Float[Array, "*runs"]:
    """The valid prediction time (VPT) in state space: how long a prediction stays close to the truth.

    The state-space counterpart of KeyCLD's eq. 16 (from Botev et al.): with `e_i` the position error
    of the worst keypoint at predicted sample `i` (`keypoint_error`), the VPT is the number of
    samples before the first `e_i > threshold`; an error that is not a number (a prediction that
    failed) counts as exceeding it. Pass the predicted samples only (not the given initial state).
    The threshold is a distance; `evaluate` uses a fraction of the range of motion.

    **Arguments:**

    - `predicted`, `truth`: keypoint positions, shape `(..., T, k)`.
    - `threshold`: the largest acceptable keypoint error (same units as the positions).
    - `dt`: the sampling interval; when given the VPT is in seconds, otherwise it is the fraction of
      the `T` samples (between 0 and 1, as in the paper's Table 1).
    - `dim`: dimension of each keypoint.

    **Returns:** the VPT per run, shape `(...)`.

    !!! example

        ```python
        vpt = cldyn.valid_prediction_time(rollout, truth, threshold=0.1)   # 1.0: never exceeded
        ```
    """
    if not threshold > 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    error = keypoint_error(predicted, truth, dim=dim)
    samples = error.shape[-1]
    exceeded = ~(error <= threshold)  # an error that is not a number (a failed prediction) exceeds it
    first = jnp.where(jnp.any(exceeded, axis=-1), jnp.argmax(exceeded, axis=-1), samples)
    first = first.astype(float)  # the default floating dtype, as integer division gives
    return first * dt if dt is not None else first / samples


def relative_error(
    predicted: Float[ArrayLike, "*runs T k"], truth: Float[ArrayLike, "*runs T k"]
) -> Float[Array, "*runs T"]:
    """The relative error of Finzi et al. (constrained HNNs) at every sample.

    $\\mathrm{err}(t) = \\|z(t) - \\hat z(t)\\| / (\\|z(t)\\| + \\|\\hat z(t)\\|)$, between 0 and 1, for
    states `z` (positions, or positions and velocities concatenated).

    **Returns:** shape `(..., T)`.
    """
    predicted, truth = _pair(predicted, truth)
    norm = jnp.linalg.norm
    return norm(predicted - truth, axis=-1) / (norm(predicted, axis=-1) + norm(truth, axis=-1))


def geometric_mean_relative_error(
    predicted: Float[ArrayLike, "*runs T k"], truth: Float[ArrayLike, "*runs T k"], *, floor: float = 1e-12
) -> Float[Array, "*runs"]:
    """The rollout error of Finzi et al.: the geometric mean over time of `relative_error`.

    $\\exp \\big( \\operatorname{mean}_t \\log \\mathrm{err}(t) \\big)$, with `err` clipped below at
    `floor` so that an exact sample (error 0, e.g. the initial state) does not make it vanish.

    **Returns:** one value per run, shape `(...)`.

    !!! example

        ```python
        gm = cldyn.geometric_mean_relative_error(jnp.concatenate([x, xd], -1), truth_state)
        ```
    """
    error = relative_error(predicted, truth)
    return jnp.exp(jnp.mean(jnp.log(jnp.maximum(error, floor)), axis=-1))


def rollout_energy(
    model: ConstrainedLagrangian, x: Float[ArrayLike, "*runs T k"], xd: Float[ArrayLike, "*runs T k"]
) -> Float[Array, "*runs T"]:
    """The model's total energy `T + V` (eq. 17) at every state of a rollout, shape `(..., T)`."""
    if not isinstance(model, ConstrainedLagrangian):
        raise TypeError(f"energies need a ConstrainedLagrangian, got {type(model).__name__}")
    x, xd = _pair(x, xd)
    flat = jax.vmap(model.energy)(x.reshape(-1, x.shape[-1]), xd.reshape(-1, xd.shape[-1]))
    return flat.reshape(x.shape[:-1])


def range_of_motion(x: Float[ArrayLike, "*runs T k"]) -> float:
    """The range of motion of keypoint data: the largest spread `max - min` of any coordinate."""
    x = np.asarray(x)
    flat = x.reshape(-1, x.shape[-1])
    return float(np.max(flat.max(axis=0) - flat.min(axis=0)))


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """Rollouts of a model from the first states of held-out runs, with their metrics.

    **Fields** (numpy arrays; `R` runs, `N` predicted samples after the initial state):

    - `ts`: times of the initial and predicted samples from the initial state, `(N + 1,)`.
    - `x`, `xd`: the rollout, `(R, N + 1, k)`; `x_true`: the measured positions.
    - `error`: the worst keypoint's position error at every sample, `(R, N + 1)`.
    - `vpt`: the valid prediction time per run as a fraction of the `N` predicted samples, `(R,)`;
      `vpt_seconds` the same in seconds.
    - `gmre`: the geometric-mean relative error of the positions per run, `(R,)`.
    - `energy`: the model's energy along its rollout `(R, N + 1)`, or `None` without energies.
    - `threshold`: the VPT threshold used (metres).
    - `failed`: per run, whether its rollout failed (a projection that did not converge: a model that
      leaves its constraints further than one step can bring it back); such a run's samples from
      the failure on are NaN, and its VPT ends there. `(R,)`.
    """

    ts: np.ndarray
    x: np.ndarray
    xd: np.ndarray
    x_true: np.ndarray
    error: np.ndarray
    vpt: np.ndarray
    vpt_seconds: np.ndarray
    gmre: np.ndarray
    energy: np.ndarray | None
    threshold: float
    failed: np.ndarray | None = None

    def error_over(self, seconds: float) -> np.ndarray:
        """The root-mean-square keypoint error per run over the first `seconds` of the rollout."""
        window = self.ts <= seconds + 1e-9
        return np.sqrt(np.mean(self.error[:, window] ** 2, axis=1))

    def summary(self) -> dict:
        """Means over runs, as plain floats.

        `vpt` and `vpt_seconds` average every run, a failed one's VPT ending at its failure. A failed
        run has no error to average, so `gmre` (the geometric mean of the runs' errors) and
        `final_error` average the runs that did not fail (NaN when none did), and `failed_runs`
        counts the others.
        """
        failed = np.zeros(self.vpt.shape, bool) if self.failed is None else np.asarray(self.failed, bool)
        completed = ~failed
        nan = float("nan")
        return {
            "runs": int(self.vpt.shape[0]),
            "vpt": float(np.mean(self.vpt)),
            "vpt_seconds": float(np.mean(self.vpt_seconds)),
            "gmre": float(np.exp(np.mean(np.log(self.gmre[completed])))) if completed.any() else nan,
            "final_error": float(np.mean(self.error[completed, -1])) if completed.any() else nan,
            "threshold": self.threshold,
            "failed_runs": int(np.sum(failed)),
        }


@eqx.filter_jit
def _evaluation_runs(model, x0, xd0, controls, *, dt, solver, dt0, stabilisation):
    def run(a, b, c):
        trajectory = rollout(
            model, a, b, c, dt, solver=solver, dt0=dt0, stabilisation=stabilisation, project=True,
            throw=False,
        )
        failed = failed_samples(trajectory)[:, None]  # scored, not raised: NaN from the failure on
        return jnp.where(failed, jnp.nan, trajectory.x), jnp.where(failed, jnp.nan, trajectory.xd)

    return jax.vmap(run)(x0, xd0, controls)


def evaluate(
    model: AbstractDynamics,
    data: Sequences,
    *,
    threshold: float,
    horizon: int | None = None,
    solver: dfx.AbstractSolver | None = None,
    dt0: float | None = None,
    stabilisation: AbstractStabilisation | None = Projection(),
    dim: int = 2,
) -> Evaluation:
    """Roll a model out from the first states of held-out runs and measure how long it stays right.

    As in the KeyCLD paper's evaluation, each rollout starts from the second sample of a run with
    the velocity from the central difference of the first three, $\\hat{\\dot x}_1 = (x_2 - x_0)/2h$
    (eq. 11), projected onto the constraint tangent space for constrained models; it runs with the
    run's controls (each held until the next sample) and is compared with the measured positions.

    **Arguments:**

    - `model`: any `AbstractDynamics`.
    - `data`: held-out runs, a `Sequences`.
    - `threshold`: the VPT threshold, a keypoint distance (see `valid_prediction_time`); for
      example 10% of `range_of_motion(data.x)`.
    - `horizon`: the number of samples to predict; all the rest of each run by default.
    - `solver`: a diffrax solver; `cldyn.RK4()` by default.
    - `dt0`: the (fixed) integration step; the sampling interval by default.
    - `stabilisation`: constraint stabilisation of `cldyn.simulate` (`Projection()` by default).
    - `dim`: dimension of each keypoint.

    The data are cast to the model's floating dtype; evaluate a float32-trained model in float64 by
    casting it first (in JAX's 64-bit mode). A rollout that fails is not an error: its samples from
    the failure on are NaN and its VPT ends there (`Evaluation.failed`); `summary()` counts such
    runs (`failed_runs`) and averages its errors over the others.

    **Returns:** an `Evaluation` with the rollouts, per-run VPT, geometric-mean relative error and
    energies (for Lagrangian models).

    !!! example

        ```python
        result = cldyn.evaluate(model, test, threshold=0.1 * cldyn.range_of_motion(test.x))
        print(result.summary())
        ```
    """
    if data.num_samples < 4:
        raise ValueError(f"evaluate needs runs of at least 4 samples, got {data.num_samples}")
    available = data.num_samples - 2
    horizon = available if horizon is None else int(horizon)
    if not 1 <= horizon <= available:
        raise ValueError(f"horizon must be between 1 and {available} samples, got {horizon}")
    dtypes = [a.dtype for a in jax.tree.leaves(eqx.filter(model, eqx.is_inexact_array))]
    if dtypes:
        data = data.astype(jnp.result_type(*dtypes))
    dt = data.dt
    x0 = data.x[:, 1]
    xd0 = central_difference(data.x[:, :3], dt)[:, 0]
    controls = data.u[:, 1 : 2 + horizon]
    ts = dt * np.arange(horizon + 1)
    solver = RK4() if solver is None else solver
    xs, xds = _evaluation_runs(
        model, x0, xd0, controls, dt=dt, solver=solver, dt0=dt0, stabilisation=stabilisation
    )
    truth = data.x[:, 1 : 2 + horizon]
    error = keypoint_error(xs, truth, dim=dim)
    vpt = valid_prediction_time(xs[:, 1:], truth[:, 1:], threshold=threshold, dim=dim)
    energy = None
    if isinstance(model, ConstrainedLagrangian):
        energy = np.asarray(rollout_energy(model, xs, xds))
    return Evaluation(
        ts=ts,
        x=np.asarray(xs),
        xd=np.asarray(xds),
        x_true=np.asarray(truth),
        error=np.asarray(error),
        vpt=np.asarray(vpt),
        vpt_seconds=np.asarray(vpt) * horizon * dt,
        gmre=np.asarray(geometric_mean_relative_error(xs[:, 1:], truth[:, 1:])),
        energy=energy,
        threshold=float(threshold),
        failed=~np.all(np.isfinite(np.asarray(xs)), axis=(1, 2)),
    )

