"""Learning dynamics from sequences of keypoint states: data, losses (KeyCLD eq. 11-13) and `fit`.

The losses take plain arrays of keypoint positions `(runs, T, k)` and controls, so the same code
serves state data (from MuJoCo or an analytic model) and keypoints that come out of an image encoder.
Every loss has the signature `loss(model, batch) -> scalar` and works for any `AbstractDynamics`:
the constrained Lagrangian of KeyCLD, its variant without constraints, and the neural ODE baseline.
"""

import abc
import csv
import dataclasses
import hashlib
import io
import json
import os
import pathlib
import tempfile
import time
import zipfile
from collections.abc import Callable
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float, PRNGKeyArray

from ._control import ZeroOrderHold
from ._custom_types import ArrayInput, Scalar
from ._integrate import AbstractStabilisation, project_state, simulate
from ._system import AbstractDynamics, ConstrainedLagrangian

_SEQUENCES_SCHEMA = "cldyn.Sequences/1"
_CHECKPOINT_MAGIC = b"CLDYN-CHECKPOINT/1\n"
CHECKPOINT_NAME = "checkpoint.eqx"
MODEL_NAME = "model.eqx"


# -- data ------------------------------------------------------------------------------------------


def _first_bad(array: np.ndarray) -> tuple[int, ...] | None:
    bad = np.argwhere(~np.isfinite(array))
    return None if bad.size == 0 else tuple(int(i) for i in bad[0])


def _as_float(value) -> Array:
    array = jnp.asarray(value)
    if not jnp.issubdtype(array.dtype, jnp.floating):
        array = array.astype(float)
    return array


class Sequences(eqx.Module):
    """Runs of keypoint states sampled at a constant interval, with their controls.

    What the losses, `fit` and `evaluate` consume. All runs share the number of samples `T`; a batch
    of runs is again a `Sequences` (it is a PyTree whose arrays all lead with the run axis).

    **Arguments:**

    - `x`: keypoint positions, shape `(runs, T, k)`.
    - `u`: controls, shape `(runs, T, l)` (the control applied from each sample to the next),
      `(runs, l)` (constant per run, as in KeyCLD's data), or `None` for none (`l = 0`).
    - `dt`: the sampling interval `h` in seconds.
    - `xd`, `xdd`: known velocities and accelerations, shape `(runs, T, k)`, or `None`. Only
      `InverseDynamics` needs them; the other losses estimate derivatives by central differences.

    Concrete inputs are checked: shapes that disagree or NaN/infinite values raise a `ValueError`
    that names the array and the first offending `(run, sample, coordinate)`.

    !!! example

        ```python
        data = cldyn.Sequences(x, u, dt=0.02)         # x: (500, 50, 2), u: (500, 1)
        train, validation = data.split(450)           # KeyCLD A.6: the last 50 runs validate
        ```
    """

    x: Float[Array, "runs T k"]
    u: Float[Array, "runs T l"]
    dt: float = eqx.field(static=True)
    xd: Float[Array, "runs T k"] | None = None
    xdd: Float[Array, "runs T k"] | None = None

    def __init__(
        self,
        x: ArrayInput,
        u: ArrayInput | None = None,
        dt: float = 1.0,
        *,
        xd: ArrayInput | None = None,
        xdd: ArrayInput | None = None,
    ):
        x = _as_float(x)
        if x.ndim != 3:
            raise ValueError(f"Sequences: x must have shape (runs, T, k), got {x.shape}")
        runs, samples, _ = x.shape
        if u is None:
            u = jnp.zeros((runs, samples, 0), dtype=x.dtype)
        u = _as_float(u)
        if u.ndim == 2:
            if u.shape[0] != runs:
                raise ValueError(f"Sequences: u has {u.shape[0]} runs but x has {runs}")
            u = jnp.broadcast_to(u[:, None, :], (runs, samples, u.shape[1]))
        if u.ndim != 3 or u.shape[:2] != (runs, samples):
            raise ValueError(
                f"Sequences: u must have shape ({runs}, {samples}, l) or ({runs}, l) to match x "
                f"{x.shape}, got {u.shape}"
            )
        dt = float(dt)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"Sequences: dt must be a positive time step, got {dt}")
        extra = {}
        for name, value in (("xd", xd), ("xdd", xdd)):
            if value is not None:
                value = _as_float(value)
                if value.shape != x.shape:
                    raise ValueError(
                        f"Sequences: {name} must have the shape of x {x.shape}, got {value.shape}"
                    )
            extra[name] = value
        for name, value in (("x", x), ("u", u), ("xd", extra["xd"]), ("xdd", extra["xdd"])):
            if value is None or isinstance(value, jax.core.Tracer):
                continue
            bad = _first_bad(np.asarray(value))
            if bad is not None:
                raise ValueError(
                    f"Sequences: {name} contains a NaN or infinite value at (run, sample, coordinate) "
                    f"= {bad}: {np.asarray(value)[bad]}"
                )
        self.x = x
        self.u = u
        self.dt = dt
        self.xd = extra["xd"]
        self.xdd = extra["xdd"]

    @property
    def num_runs(self) -> int:
        """The number of runs."""
        return self.x.shape[0]

    @property
    def num_samples(self) -> int:
        """The number `T` of samples per run."""
        return self.x.shape[1]

    @property
    def size(self) -> int:
        """The number `k` of keypoint coordinates."""
        return self.x.shape[2]

    @property
    def num_inputs(self) -> int:
        """The number `l` of controls."""
        return self.u.shape[2]

    def take(self, runs) -> "Sequences":
        """The runs at the given indices (an integer array or a slice); works under `jax.jit`."""
        return jax.tree.map(lambda a: a[runs], self)

    def split(self, first: int | float) -> tuple["Sequences", "Sequences"]:
        """Split the runs in two, in order: the first `first` runs (or that fraction) and the rest.

        KeyCLD (appendix A.6) trains on the first 450 of 500 runs and validates on the last 50.
        """
        count = int(round(first * self.num_runs)) if isinstance(first, float) else int(first)
        if not 0 < count < self.num_runs:
            raise ValueError(f"split: need 0 < first < {self.num_runs} runs, got {first}")
        return self.take(slice(0, count)), self.take(slice(count, None))

    def astype(self, dtype) -> "Sequences":
        """The same data with floating arrays cast to `dtype`."""
        return jax.tree.map(lambda a: a.astype(dtype), self)

    @classmethod
    def from_recording(
        cls, recording: Any, *, origin: ArrayInput | None = None, clean: bool = False
    ) -> "Sequences":
        """From a `cldyn.mujoco.Recording` (or anything with `x`, `u`, `dt` and optionally `xd`, `xdd`).

        **Arguments:**

        - `recording`: the recorded runs.
        - `origin`: a point `(d,)` subtracted from every keypoint (e.g. the pivot, so that KeyCLD's
          `Anchor` constraints at the origin apply); none by default.
        - `clean`: use the noise-free positions `x_clean` instead of the observed `x`.

        **Returns:** the `Sequences`, with MuJoCo's keypoint velocities and accelerations as `xd`,
        `xdd`.
        """
        x = np.asarray(recording.x_clean if clean else recording.x, dtype=float)
        xd = getattr(recording, "xd", None)
        xdd = getattr(recording, "xdd", None)
        if origin is not None:
            origin = np.asarray(origin, dtype=float).reshape(-1)
            d = origin.shape[0]
            if x.shape[-1] % d:
                raise ValueError(f"origin has {d} coordinates; keypoints of size {x.shape[-1]} do not split")
            x = x - np.tile(origin, x.shape[-1] // d)
        return cls(x, recording.u, float(recording.dt), xd=xd, xdd=xdd)

    def save(self, path: "str | os.PathLike") -> pathlib.Path:
        """Save to a compressed `.npz` file (`.npz` appended if missing); returns the path."""
        path = pathlib.Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"x": np.asarray(self.x), "u": np.asarray(self.u)}
        for name in ("xd", "xdd"):
            if getattr(self, name) is not None:
                arrays[name] = np.asarray(getattr(self, name))
        meta = json.dumps({"schema": _SEQUENCES_SCHEMA, "dt": self.dt})
        np.savez_compressed(path, metadata=np.array(meta), **arrays)
        return path

    @classmethod
    def load(cls, path: "str | os.PathLike") -> "Sequences":
        """Load a file written by `save`; a missing or corrupt file raises an error naming it."""
        path = pathlib.Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        try:
            with np.load(path, allow_pickle=False) as npz:
                contents = {name: npz[name] for name in npz.files}
            meta = json.loads(str(contents["metadata"]))
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as error:
            raise ValueError(f"{path}: not a readable Sequences file ({error})") from error
        if meta.get("schema") != _SEQUENCES_SCHEMA:
            raise ValueError(f"{path}: schema {meta.get('schema')!r}, expected {_SEQUENCES_SCHEMA!r}")
        try:
            x, u, dt = contents["x"], contents["u"], meta["dt"]
            return cls(x, u, dt, xd=contents.get("xd"), xdd=contents.get("xdd"))
        except KeyError as error:
            raise ValueError(f"{path}: missing {error}") from error


def central_difference(x: Float[Array, "*batch T k"], dt: float) -> Float[Array, "*batch T-2 k"]:
    """The central difference $(x_{i+1} - x_{i-1}) / 2h$ along the time axis (eq. 11, 12).

    **Arguments:**

    - `x`: samples along the second-to-last axis, shape `(..., T, k)`.
    - `dt`: the interval `h`.

    **Returns:** the derivative at samples `1 .. T-2`, shape `(..., T-2, k)`.
    """
    return (x[..., 2:, :] - x[..., :-2, :]) / (2 * dt)


def _per_state(fn, *arrays):
    """`fn` mapped over the leading (runs, time) axes of every array."""
    return jax.vmap(jax.vmap(fn))(*arrays)


def _project_velocities(model, x, xd):
    """Velocities projected onto `DPhi(x) xd = 0` for constrained models; unchanged otherwise."""
    if not isinstance(model, ConstrainedLagrangian) or model.num_constraints == 0:
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


# -- losses ----------------------------------------------------------------------------------------


class AbstractLoss(eqx.Module):
    """A training loss `loss(model, batch) -> scalar` over a batch of `Sequences`.

    Losses add up and scale: `Collocation() + 0.1 * Rollout()` is a `LossSum`.
    """

    @abc.abstractmethod
    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
        """The loss of `model` on `batch`, a scalar."""

    def __add__(self, other: "AbstractLoss") -> "LossSum":
        if not isinstance(other, AbstractLoss):
            return NotImplemented
        return LossSum(_terms(self) + _terms(other))

    def __rmul__(self, weight: float) -> "LossSum":
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
    """

    terms: tuple[tuple[float, AbstractLoss], ...] = eqx.field(static=True)

    def __check_init__(self):
        for weight, loss in self.terms:
            if not isinstance(loss, AbstractLoss) or not np.isfinite(weight):
                raise ValueError(f"LossSum takes (finite weight, loss) pairs, got ({weight}, {loss})")

    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
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


class Rollout(AbstractLoss):
    """A multi-step rollout loss: from every state, predict the next `steps` positions.

    Each sample `i` with a central-difference velocity $\\hat{\\dot x}_i$ (eq. 11) starts a rollout of
    `steps` steps of `h`, with the controls of the samples it crosses; the loss is the mean squared
    position error over all starts and steps, divided by `h^4` so that, like `Collocation`, it is in
    units of acceleration squared. By default the rollout takes explicit Euler steps,
    $x_{j+1} = x_j + h \\dot x_j$, $\\dot x_{j+1} = \\dot x_j + h \\ddot x(x_j, \\dot x_j, u_j)$,
    as the KeyCLD authors' code does (4 steps); any diffrax solver integrates through
    `cldyn.simulate` instead (constrained models start from the projected velocity).

    Explicit Euler is only first-order accurate: on exact data its best fit overestimates
    accelerations by the factor `n^2 / (n (n - 1))` at step `n`. Combine it with `Collocation`, or
    pass a higher-order solver such as `cldyn.RK4()` where the bias matters.

    **Arguments:**

    - `steps`: the number of steps `n` of every rollout.
    - `solver`: `None` for explicit Euler, or a diffrax solver (fixed steps of `h`).
    - `stabilisation`: the constraint stabilisation of `cldyn.simulate` when a solver is given;
      none by default (rollouts are short).
    - `project`: project each initial velocity onto the constraint tangent space (always done when
      a solver is given).

    !!! example

        ```python
        loss = cldyn.Collocation() + cldyn.Rollout(steps=4)
        ```
    """

    steps: int = eqx.field(static=True, default=4)
    solver: dfx.AbstractSolver | None = None
    stabilisation: AbstractStabilisation | None = None
    project: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.steps < 1:
            raise ValueError(f"Rollout needs steps >= 1, got {self.steps}")

    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
        n, h = self.steps, batch.dt
        _check_samples(f"Rollout(steps={n})", batch, n + 2)
        _check_model("Rollout", model, batch)
        # samples 1 .. T-1-n start a rollout: each has a central difference and n samples after it
        starts = batch.num_samples - 1 - n
        xd_all = central_difference(batch.x, h)  # samples 1 .. T-2
        x0 = batch.x[:, 1 : 1 + starts]
        xd0 = xd_all[:, :starts]
        if self.project or self.solver is not None:
            xd0 = _project_velocities(model, x0, xd0)
        # targets[r, i, j] = x[r, 1 + i + j + 1], controls[r, i, j] = u[r, 1 + i + j]
        offsets = np.arange(starts)[:, None] + np.arange(n)[None, :]
        targets = batch.x[:, 2 + offsets]
        controls = batch.u[:, 1 + offsets]
        if self.solver is None:
            predicted = _per_state(lambda a, b, c: _euler(model, a, b, c, h), x0, xd0, controls)
        else:
            ts = h * np.arange(n + 1)
            constrained = isinstance(model, ConstrainedLagrangian) and model.num_constraints > 0

            def run(a, b, c):
                traj = simulate(
                    model, a, b, ts, control=ZeroOrderHold(c, h), solver=self.solver, dt0=h,
                    stabilisation=self.stabilisation, project=constrained,
                )
                return traj.x[1:]

            predicted = _per_state(run, x0, xd0, controls)
        return jnp.mean(jnp.sum((predicted - targets) ** 2, axis=-1)) / h**4


def _euler(model, x, xd, controls, h):
    def step(state, u):
        x, xd = state
        xdd = model.acceleration(x, xd, u)
        x, xd = x + h * xd, xd + h * xdd
        return (x, xd), x

    _, xs = jax.lax.scan(step, (x, xd), controls)
    return xs


class MultipleShooting(AbstractLoss):
    """Multiple shooting: every run is cut into segments, each integrated by `cldyn.simulate`.

    Segment `s` starts at sample `1 + s * segment` from the measured position and the
    central-difference velocity (eq. 11; projected onto the constraint tangent space for constrained
    models) and is integrated over `segment` intervals with the run's controls; the loss is the mean
    squared position error over all predicted samples, divided by `h^4` as in `Rollout`. The segment
    starts come from the data rather than being free variables, so segments are independent.

    **Arguments:**

    - `segment`: the number of intervals per segment.
    - `solver`: a diffrax solver; `cldyn.RK4()` (fixed steps) by default.
    - `dt0`: the integration step; the sampling interval by default.
    - `stabilisation`: the constraint stabilisation of `cldyn.simulate`; none by default.

    !!! example

        ```python
        loss = cldyn.MultipleShooting(segment=10)
        ```
    """

    segment: int = eqx.field(static=True, default=10)
    solver: dfx.AbstractSolver | None = None
    dt0: float | None = eqx.field(static=True, default=None)
    stabilisation: AbstractStabilisation | None = None

    def __check_init__(self):
        if self.segment < 1:
            raise ValueError(f"MultipleShooting needs segment >= 1, got {self.segment}")

    def __call__(self, model: AbstractDynamics, batch: Sequences) -> Scalar:
        from ._integrate import RK4

        n, h = self.segment, batch.dt
        _check_samples(f"MultipleShooting(segment={n})", batch, n + 3)
        _check_model("MultipleShooting", model, batch)
        count = (batch.num_samples - 2) // n
        starts = 1 + n * np.arange(count)
        xd_all = central_difference(batch.x, h)
        x0 = batch.x[:, starts]
        xd0 = _project_velocities(model, x0, xd_all[:, starts - 1])
        window = starts[:, None] + np.arange(n + 1)[None, :]
        targets = batch.x[:, window[:, 1:]]
        controls = batch.u[:, window]
        ts = h * np.arange(n + 1)
        solver = RK4() if self.solver is None else self.solver
        dt0 = h if self.dt0 is None else self.dt0
        constrained = isinstance(model, ConstrainedLagrangian) and model.num_constraints > 0

        def run(a, b, c):
            traj = simulate(
                model, a, b, ts, control=ZeroOrderHold(c, h), solver=solver,
                stabilisation=self.stabilisation, project=constrained, dt0=dt0,
            )
            return traj.x[1:]

        predicted = _per_state(run, x0, xd0, controls)
        return jnp.mean(jnp.sum((predicted - targets) ** 2, axis=-1)) / h**4


class InverseDynamics(AbstractLoss):
    """The inverse-dynamics loss, when accelerations and controls are measured.

    $L = \\operatorname{mean}_i \\| \\ddot x_i - \\ddot x(x_i, \\dot x_i, u_i) \\|^2$ over every sample,
    with the measured accelerations `batch.xdd` and velocities `batch.xd` (central differences on the
    interior samples when `batch.xd` is absent).

    **Arguments:**

    - `project`: project the velocities onto the constraint tangent space first.
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


# -- checkpoints -----------------------------------------------------------------------------------


class CheckpointError(ValueError):
    """A checkpoint that cannot be read: missing, corrupt, or made for another model or optimiser."""


class NonFiniteLossError(RuntimeError):
    """`fit` met a NaN or infinite loss or gradient and stopped.

    **Attributes:** `step` (the step that failed), `model` (the last good model), `checkpoint`
    (the path of the last good checkpoint, or `None`).
    """

    def __init__(self, message: str, *, step: int, model: Any, checkpoint: pathlib.Path | None):
        super().__init__(message)
        self.step = step
        self.model = model
        self.checkpoint = checkpoint


def _atomic_write(path: pathlib.Path, data: bytes) -> None:
    """Write `data` to `path` so that a reader sees either the old file or the whole new one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.unlink(temporary)
        raise
    try:
        directory = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(directory)
    except OSError:
        pass
    finally:
        os.close(directory)


def _serialise(tree) -> bytes:
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, tree)
    return buffer.getvalue()


def save_checkpoint(path: "str | os.PathLike", tree, header: dict) -> None:
    """Write `tree` (equinox serialisation) and a JSON `header` to one file, atomically."""
    payload = _serialise(tree)
    header = dict(header, sha256=hashlib.sha256(payload).hexdigest(), payload_bytes=len(payload))
    text = json.dumps(header).encode()
    _atomic_write(pathlib.Path(path), _CHECKPOINT_MAGIC + text + b"\n" + payload)


def load_checkpoint(path: "str | os.PathLike", like) -> tuple[Any, dict]:
    """Read a checkpoint written by `save_checkpoint` into the structure of `like`.

    **Returns:** `(tree, header)`. Raises `CheckpointError`, naming the file, when it is truncated,
    corrupt, or does not match `like`.
    """
    path = pathlib.Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise CheckpointError(f"checkpoint {path}: cannot read it ({error})") from error
    if not raw.startswith(_CHECKPOINT_MAGIC):
        raise CheckpointError(f"checkpoint {path} is corrupt: it does not start with a cldyn header")
    end = raw.find(b"\n", len(_CHECKPOINT_MAGIC))
    try:
        header = json.loads(raw[len(_CHECKPOINT_MAGIC) : end])
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise CheckpointError(f"checkpoint {path} is corrupt: unreadable header ({error})") from error
    payload = raw[end + 1 :]
    digest = hashlib.sha256(payload).hexdigest()
    if len(payload) != header.get("payload_bytes") or digest != header.get("sha256"):
        raise CheckpointError(
            f"checkpoint {path} is corrupt: its data do not match the checksum in its header "
            "(truncated or modified file)"
        )
    try:
        tree = eqx.tree_deserialise_leaves(io.BytesIO(payload), like)
    except Exception as error:  # equinox/numpy raise several types for a mismatch
        raise CheckpointError(
            f"checkpoint {path} does not match this model and optimiser ({type(error).__name__}: {error})"
        ) from error
    return tree, header


# -- fit -------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What `fit` returns.

    **Fields:**

    - `model`: the trained model.
    - `history`: one dict per logged step: `step`, `loss` (mean training loss since the previous
      record), `validation` (when computed), `seconds` (training time so far).
    - `step`: the number of optimiser steps taken in total.
    - `seconds`: training time in seconds, over all sessions of a resumed fit.
    - `out`: the output directory, or `None`.
    """

    model: Any
    history: list[dict]
    step: int
    seconds: float
    out: pathlib.Path | None


def _trainable_spec(model, trainable):
    if trainable is None:
        return eqx.is_inexact_array
    if callable(trainable) and not isinstance(trainable, eqx.Module):
        spec = trainable(model)
        # a per-leaf filter such as `eqx.is_inexact_array` answers for the whole model with one bool
        return trainable if isinstance(spec, bool) else spec
    return trainable


def _partition(model, trainable):
    params, static = eqx.partition(model, _trainable_spec(model, trainable))
    params, frozen = eqx.partition(params, eqx.is_inexact_array)
    return params, eqx.combine(static, frozen)


def _cast(tree, dtype):
    if dtype is None:
        return tree
    return jax.tree.map(lambda a: a.astype(dtype) if eqx.is_inexact_array(a) else a, tree)


def _all_finite(tree) -> Array:
    leaves = [jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(eqx.filter(tree, eqx.is_inexact_array))]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


@eqx.filter_jit
def _train_step(params, static, opt_state, data, key, step, *, loss, optimizer, batch_size):
    runs = jax.tree.leaves(data)[0].shape[0]
    step_key = jax.random.fold_in(key, step)
    if batch_size >= runs:
        indices = jax.random.permutation(step_key, runs)
    else:
        indices = jax.random.choice(step_key, runs, (batch_size,), replace=False)
    batch = jax.tree.map(lambda a: a[indices], data)

    def objective(p):
        return loss(eqx.combine(p, static), batch)

    value, grads = eqx.filter_value_and_grad(objective)(params)
    updates, new_opt_state = optimizer.update(grads, opt_state, params)
    new_params = eqx.apply_updates(params, updates)
    finite = jnp.isfinite(value) & _all_finite(grads)
    return new_params, new_opt_state, value, finite


@eqx.filter_jit
def _evaluate_loss(model, data, *, loss):
    return loss(model, data)


def _key_data(key) -> list[int]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return [int(v) for v in np.asarray(key).reshape(-1)]


def _json_value(value):
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


def _write_history(out: pathlib.Path, history: list[dict], fmt: str) -> None:
    if fmt == "json":
        _atomic_write(out / "history.json", json.dumps(history, indent=1).encode())
        return
    buffer = io.StringIO()
    fields = ["step", "loss", "validation", "seconds"]
    writer = csv.DictWriter(buffer, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    for row in history:
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in writer.fieldnames})
    _atomic_write(out / "history.csv", buffer.getvalue().encode())


def fit(
    model: eqx.Module,
    data: "Sequences | Any",
    *,
    loss: Callable[[Any, Any], Scalar],
    steps: int,
    key: PRNGKeyArray,
    optimizer: optax.GradientTransformation | None = None,
    batch_size: int = 32,
    validation: "Sequences | Any | None" = None,
    validate_every: int = 100,
    log_every: int = 10,
    out: "str | os.PathLike | None" = None,
    checkpoint_every: int = 500,
    resume: bool = False,
    history_format: str = "json",
    trainable: Any = None,
    dtype: Any = jnp.float32,
    progress: bool = True,
    callback: Callable[[int, Any, float], None] | None = None,
) -> FitResult:
    """Fit the parameters of a model to sequences of keypoint states by stochastic gradient descent.

    Every step draws `batch_size` runs (without replacement, from `key` folded with the step number,
    so a resumed fit draws the same batches), evaluates `loss(model, batch)`, and applies one
    optimiser update to the trainable parameters; the step is compiled once with `eqx.filter_jit`.

    **Arguments:**

    - `model`: the model, e.g. `cldyn.keycld_model(...)` or `cldyn.SecondOrderNeuralODE(...)`.
    - `data`: the training runs, a `Sequences` (or any PyTree whose arrays lead with the run axis).
    - `loss`: `loss(model, batch) -> scalar`, e.g. `cldyn.Collocation()` (eq. 11-13).
    - `steps`: the total number of optimiser steps (a resumed fit continues up to it).
    - `key`: a `jax.random` key for the minibatches.
    - `optimizer`: an optax optimiser; by default Adam with learning rate `3e-4` after element-wise
      gradient clipping at 5, as in the KeyCLD authors' code.
    - `batch_size`: runs per step.
    - `validation`: held-out runs; their loss is computed every `validate_every` steps and at the end.
    - `log_every`: steps between history records (each the mean training loss since the last).
    - `out`: a directory for `history.json` (or `.csv`), `checkpoint.eqx` and the final `model.eqx`;
      nothing is written without it.
    - `checkpoint_every`: steps between checkpoints (and one at the end). A checkpoint holds the
      model, the optimiser state, the step, the key and the history, in one file written atomically
      (temporary file, `fsync`, `os.replace`), so an interrupted write never damages the last one.
    - `resume`: continue from `out/checkpoint.eqx` if it exists (the model and optimiser given
      must have the same structure). The result is the same as an uninterrupted fit.
    - `history_format`: `"json"` or `"csv"`.
    - `trainable`: which parameters to train: `None` (every inexact array), a filter-spec PyTree of
      booleans (a prefix of the model, as for `eqx.partition`), a function `model -> spec`, or a
      per-leaf filter function. Other leaves are frozen.
    - `dtype`: floating dtype of the parameters and data during training; `float32` by default
      (fast, and accurate enough for the finite differences of KeyCLD's data). `None` keeps the
      dtypes given; `float64` needs `jax_enable_x64`.
    - `progress`: show a tqdm progress bar.
    - `callback`: `callback(step, model, loss)` after every step (and checkpoint).

    **Returns:** a `FitResult` with the trained model and the history.

    A non-finite loss or gradient stops the fit with a `NonFiniteLossError` that names the step;
    the update is not applied, the last checkpoint is left untouched, and the error carries the last
    good model. A checkpoint that cannot be read raises a `CheckpointError` naming the file.

    !!! example

        ```python
        model = cldyn.keycld_model(4, 2, cldyn.Stack([cldyn.Anchor(0), cldyn.Distance(0, 1)]),
                                   key=jax.random.key(0))
        result = cldyn.fit(model, train, loss=cldyn.Collocation(), steps=2000, batch_size=32,
                           key=jax.random.key(1), validation=validation, out="runs/acrobot")
        ```
    """
    if steps < 0 or batch_size < 1 or validate_every < 1 or log_every < 1 or checkpoint_every < 1:
        raise ValueError(
            "fit needs steps >= 0 and batch_size, validate_every, log_every, checkpoint_every >= 1"
        )
    if history_format not in ("json", "csv"):
        raise ValueError(f"history_format must be 'json' or 'csv', got {history_format!r}")
    if dtype is not None and jnp.dtype(dtype) == jnp.float64 and not jax.config.jax_enable_x64:
        raise ValueError("dtype float64 needs jax.config.update('jax_enable_x64', True)")
    if resume and out is None:
        raise ValueError("resume=True needs the output directory `out`")
    optimizer = optax.chain(optax.clip(5.0), optax.adam(3e-4)) if optimizer is None else optimizer
    model = _cast(model, dtype)
    data = _cast(data, dtype)
    if validation is not None:
        validation = _cast(validation, dtype)
    params, static = _partition(model, trainable)
    opt_state = optimizer.init(params)
    out = None if out is None else pathlib.Path(out)
    checkpoint = None if out is None else out / CHECKPOINT_NAME
    key_data = _key_data(key)

    start, history, elapsed = 0, [], 0.0
    if resume and checkpoint.exists():
        (model, opt_state), header = load_checkpoint(checkpoint, (model, opt_state))
        if header.get("key") != key_data:
            raise CheckpointError(
                f"checkpoint {checkpoint} was written by a fit with another key; pass the same key to resume"
            )
        params, static = _partition(model, trainable)
        start, history, elapsed = int(header["step"]), list(header["history"]), float(header["seconds"])
    saved_step = start if (resume and checkpoint is not None and checkpoint.exists()) else None

    def save(step, model, opt_state, seconds):
        nonlocal saved_step
        if checkpoint is None:
            return
        header = {"step": step, "key": key_data, "history": history, "seconds": seconds}
        save_checkpoint(checkpoint, (model, opt_state), header)
        _write_history(out, history, history_format)
        saved_step = step

    def validate(model):
        if validation is None:
            return None
        return _json_value(_evaluate_loss(model, validation, loss=loss))

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, initial=start, desc="fit", unit="step", dynamic_ncols=True)
    losses: list[float] = []
    clock = time.perf_counter()
    step = start
    try:
        while step < steps:
            new_params, new_opt_state, value, finite = _train_step(
                params, static, opt_state, data, key, jnp.asarray(step),
                loss=loss, optimizer=optimizer, batch_size=batch_size,
            )
            value = float(value)
            if not bool(finite):
                good = eqx.combine(params, static)
                where = "no checkpoint was written" if saved_step is None else (
                    f"the last good checkpoint is {checkpoint} (step {saved_step}), left untouched"
                )
                raise NonFiniteLossError(
                    f"fit: non-finite loss or gradient at step {step + 1} (loss = {value}); stopped "
                    f"without applying the update; {where}. Lower the learning rate, check the data for "
                    "outliers, or start from a checkpoint.",
                    step=step + 1,
                    model=good,
                    checkpoint=None if saved_step is None else checkpoint,
                )
            params, opt_state, step = new_params, new_opt_state, step + 1
            losses.append(value)
            if bar is not None:
                bar.update(1)
            last = step == steps
            if step % log_every == 0 or step % validate_every == 0 or last:
                record = {"step": step, "loss": _json_value(np.mean(losses)) if losses else None}
                losses = []
                if step % validate_every == 0 or last:
                    record["validation"] = validate(eqx.combine(params, static))
                record["seconds"] = elapsed + time.perf_counter() - clock
                history.append(record)
                if bar is not None:
                    shown = {k: record.get(k) for k in ("loss", "validation")}
                    bar.set_postfix({k: f"{v:.3g}" for k, v in shown.items() if v is not None})
            if step % checkpoint_every == 0 or last:
                save(step, eqx.combine(params, static), opt_state, elapsed + time.perf_counter() - clock)
            if callback is not None:
                callback(step, eqx.combine(params, static), value)
    except KeyboardInterrupt:
        if saved_step != step:
            save(step, eqx.combine(params, static), opt_state, elapsed + time.perf_counter() - clock)
        raise
    finally:
        if bar is not None:
            bar.close()
    seconds = elapsed + time.perf_counter() - clock
    model = eqx.combine(params, static)
    if out is not None:
        if saved_step != step:
            save(step, model, opt_state, seconds)
        _atomic_write(out / MODEL_NAME, _serialise(model))
        _write_history(out, history, history_format)
    return FitResult(model=model, history=history, step=step, seconds=seconds, out=out)
