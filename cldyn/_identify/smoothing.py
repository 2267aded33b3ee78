"""From measured positions to the data the weak form needs, in physical time: Savitzky-Golay smoothing
differentiation, test functions, decimation and the prepared runs. The settings are chosen from the
data (`choice.py`) unless given."""

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._coordinates import AbstractCoordinate, JointMap

_STEPS_PER_TIMESCALE = 10  # rollout steps per time scale of the motion, at least


class Smoothing(eqx.Module):
    """How positions become the equations that identification regresses; every length in seconds.

    Positions and velocities come from Savitzky-Golay smoothing differentiation: at every sample a
    polynomial of degree `order` is fitted by least squares to the samples within `window` seconds
    centred on it, and its value and derivative there are the estimates (half a window is lost at
    each end of a run). Accelerations are never needed by the regression: the equations of motion are
    integrated against smooth test functions $\\psi(t) = (1 - s^2)^4$ of `test_width` seconds, placed
    every `test_stride` seconds, and integration by parts moves the time derivative onto $\\psi$
    (the weak form). Data sampled faster than the smoothed motion needs are decimated after smoothing:
    the smoothed positions and velocities are taken every few samples, and the controls averaged over
    each interval, so that 2 kHz data cost no more than the motion requires.

    Every setting left at `None` is chosen from the data (`Smoothing.choose`; see
    `cldyn.SmoothingChoice` for the criteria): the window minimises the estimated mean-square error of
    the smoothed velocities, given the position noise estimated from high-order differences; the test
    functions span twice the motion's time scale (the ratio of RMS velocity to RMS acceleration). The
    choice, with the noise and time scale it rests on, is recorded in the report.

    **Arguments:**

    - `window`: the Savitzky-Golay window, seconds; chosen from the data by default.
    - `order`: its polynomial degree, at least 2.
    - `test_width`: the width of each test function, seconds; chosen from the data by default.
    - `test_stride`: seconds between the centres of consecutive test functions; a sixth of the width
      by default.
    - `decimate`: whether to thin out the smoothed samples where the rate is far above what the
      smoothed motion needs (the result is the same to quadrature accuracy, at a fraction of the cost).

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                smoothing=cldyn.Smoothing(window=0.1, test_width=0.3))
        ```
    """

    window: float | None = eqx.field(static=True, default=None)
    order: int = eqx.field(static=True, default=6)
    test_width: float | None = eqx.field(static=True, default=None)
    test_stride: float | None = eqx.field(static=True, default=None)
    decimate: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        for name in ("window", "test_width", "test_stride"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"Smoothing: {name} must be a positive number of seconds, got {value!r}")
        if not (isinstance(self.order, int) and self.order >= 2):
            raise ValueError(f"Smoothing: order must be an integer >= 2, got {self.order!r}")
        if (
            self.test_stride is not None
            and self.test_width is not None
            and self.test_stride > self.test_width
        ):
            raise ValueError(
                f"Smoothing: test_stride ({self.test_stride} s) must not exceed test_width "
                f"({self.test_width} s)"
            )

    def choose(self, x: ArrayLike, dt: float) -> "SmoothingChoice":
        """The settings for positions `x` `(runs, T, k)` sampled every `dt` seconds: those given, and
        the others chosen from the data. **Returns:** a `cldyn.SmoothingChoice`."""
        from .choice import choose

        return choose(self, np.asarray(x, dtype=float), float(dt))


def savitzky_golay(window: int, order: int) -> np.ndarray:
    """The `(3, window)` Savitzky-Golay filters for value, first and second derivative at the centre,
    per unit sample interval (divide by `dt` and `dt**2`)."""
    half = window // 2
    # offsets scaled to [-1, 1]: the Vandermonde matrix of raw offsets is ill-conditioned for long windows
    scaled = np.arange(-half, half + 1, dtype=float) / max(half, 1)
    vandermonde = scaled[:, None] ** np.arange(order + 1)[None, :]
    fit = np.linalg.pinv(vandermonde)  # (order + 1, window): polynomial coefficients in the scaled offset
    return np.stack([fit[0], fit[1] / max(half, 1), 2.0 * fit[2] / max(half, 1) ** 2])


@dataclasses.dataclass(frozen=True)
class SmoothingChoice:
    """The smoothing and weak-form settings `identify` used, in samples and seconds, with the
    estimates they were chosen from.

    **Fields:**

    - `dt`: the sampling interval of the data, seconds.
    - `window`, `order`: the Savitzky-Golay window (samples of the data, odd) and degree.
    - `step`: the decimation: smoothed samples are kept every `step` samples of the data.
    - `test_width`, `test_stride`: the test functions, in kept samples (`interval = step * dt` each).
    - `noise`: the position noise estimated from the data (metres, standard deviation): the smallest
      over orders 2 to 6 of a robust (median absolute) estimate from `d`-th differences, which white
      noise inflates by `sqrt(binom(2d, d))` and a smooth motion hardly touches.
    - `timescale`: the motion's time scale, RMS velocity / RMS acceleration of the smoothed keypoints
      (noise removed), seconds; a sinusoid of angular frequency `w` has `1 / w`.
    - `velocity_error`: the estimated RMS error of the smoothed velocities at the chosen window.
    - `chosen`: for each of `window`, `test_width` and `step`, how it was set: `"given"` or the
      criterion that chose it.

    The criteria: the **window** minimises the estimated mean-square velocity error, the noise part
    `noise^2 |h_1|^2` of the filter `h_1` plus the squared bias, estimated from the difference to the
    velocities of a window 1.6 times shorter (bias grows as `window^order`), less that difference's
    noise part; at least `order + 3` samples. The **test functions** span `2 * timescale` (their
    half-power frequency is then about twice the motion's RMS frequency), at least 15 samples of the
    data and at most a third of a run; the stride is a sixth of the width. **Decimation** keeps a
    sample every `min(window / 10, test_width / 24)` seconds (rounded down to samples of the data),
    or every `test_width / 24` where the velocity noise left by the smoothing is below `1e-4` of the
    RMS velocity (nothing then to alias).
    """

    dt: float
    window: int
    order: int
    step: int
    test_width: int
    test_stride: int
    noise: float
    timescale: float
    velocity_error: float
    chosen: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def interval(self) -> float:
        """Seconds between the kept samples."""
        return self.step * self.dt

    @property
    def margin(self) -> int:
        """Samples of the data lost at each end of a run."""
        return self.window // 2

    @property
    def correlation(self) -> float:
        """Rows of the weak equations per independent one (test functions overlap)."""
        return self.test_width / self.test_stride

    @property
    def substeps(self) -> int:
        """Integration steps per kept interval in identify's rollouts: enough that a step is at most a
        tenth of the motion's time scale (1 wherever the kept samples resolve the motion that finely)."""
        if not (math.isfinite(self.timescale) and self.timescale > 0):
            return 1
        return max(1, math.ceil(_STEPS_PER_TIMESCALE * self.interval / self.timescale - 1e-9))

    def grid(self, samples: int) -> np.ndarray:
        """The indices of the kept samples in runs of `samples` samples of the data."""
        return np.arange(self.margin, samples - self.margin, self.step)

    def smooth(self, x: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Smoothed `(x, xd, xdd)` at the kept samples of positions `x` `(runs, T, k)`.

        **Returns:** three arrays of shape `(runs, len(grid(T)), k)`.
        """
        x = np.asarray(x, dtype=float)
        if x.ndim != 3:
            raise ValueError(f"positions must have shape (runs, T, k), got {x.shape}")
        if x.shape[1] < self.window:
            raise ValueError(
                f"runs of {x.shape[1]} samples ({(x.shape[1] - 1) * self.dt:.3g} s) are shorter than the "
                f"smoothing window of {self.window} samples ({self.window * self.dt:.3g} s)"
            )
        filters = savitzky_golay(self.window, self.order) / np.array([1.0, self.dt, self.dt**2])[:, None]
        windows = np.lib.stride_tricks.sliding_window_view(x, self.window, axis=1)[:, :: self.step]
        out = np.einsum("rtkw,dw->drtk", windows, filters)
        return out[0], out[1], out[2]

    def test_functions(self, samples: int) -> "TestFunctions":
        """The test functions over runs of `samples` kept samples."""
        half = self.test_width // 2
        centres = np.arange(half, samples - half, self.test_stride)
        t = np.arange(samples)[None, :] - centres[:, None]
        s = t / (half + 1)
        inside = np.abs(s) < 1
        interval = self.interval
        psi = np.where(inside, (1 - s**2) ** 4, 0.0)
        dpsi = np.where(inside, -8 * s * (1 - s**2) ** 3 / ((half + 1) * interval), 0.0)
        norm = psi.sum(axis=1, keepdims=True) * interval
        return TestFunctions(psi / norm * interval, dpsi / norm * interval)

    def to_dict(self) -> dict[str, Any]:
        """The settings for reports, in samples and seconds."""
        return {
            "velocities": "savitzky-golay",
            "window": self.window,
            "window_seconds": self.window * self.dt,
            "order": self.order,
            "decimation": self.step,
            "interval_seconds": self.interval,
            "rollout_substeps": self.substeps,
            "equations": "weak form, test functions (1 - s^2)^4",
            "test_width": self.test_width,
            "test_width_seconds": self.test_width * self.interval,
            "test_stride": self.test_stride,
            "test_stride_seconds": self.test_stride * self.interval,
            "noise": self.noise,
            "timescale_seconds": self.timescale,
            "velocity_error": self.velocity_error,
            "chosen": dict(self.chosen),
        }


@dataclasses.dataclass(frozen=True)
class TestFunctions:
    """Smooth bumps `psi_n(t)` with unit integral and their time derivatives, shape `(n, samples)`
    each, already multiplied by the sample interval (the quadrature weight)."""

    __test__ = False  # not a pytest class

    psi: np.ndarray
    dpsi: np.ndarray

    @property
    def count(self) -> int:
        """The number `n` of test functions."""
        return self.psi.shape[0]

    def weak(self, momentum: ArrayLike, rate: ArrayLike, direct: ArrayLike) -> np.ndarray:
        """`int psi (L xdd + c) dt = int [-psi' (L xd) - psi (DL[xd] xd) + psi c] dt` for arrays
        `(runs, T, ...)`: `(runs, n, ...)`."""
        return (
            -np.einsum("nt,rt...->rn...", self.dpsi, np.asarray(momentum))
            - np.einsum("nt,rt...->rn...", self.psi, np.asarray(rate))
            + np.einsum("nt,rt...->rn...", self.psi, np.asarray(direct))
        )

    def support(self, mask: np.ndarray) -> np.ndarray:
        """Which test functions of each run touch a flagged sample: `mask` `(runs, T)` -> `(runs, n)`."""
        return np.einsum("nt,rt->rn", (self.psi > 0).astype(float), mask.astype(float)) > 0


@dataclasses.dataclass(frozen=True)
class Prepared:
    """Smoothed runs at the kept samples, with the measurement and the controls there.

    `u` is the control averaged over the interval centred on each kept sample (what the weak form's
    quadrature needs); `u_hold` the control averaged over the interval that starts there (held until
    the next kept sample, it gives the same impulse as the data's controls: what rollouts need);
    `x_measured` the measured positions at the kept samples; `excluded` flags samples that the
    equations must leave out (a joint at its limit); `dt` the interval between kept samples.
    """

    x: np.ndarray  # (runs, T', k)
    xd: np.ndarray
    xdd: np.ndarray
    u: np.ndarray  # (runs, T', l)
    q: np.ndarray  # (runs, T', m) unwrapped joint coordinates
    u_hold: np.ndarray  # (runs, T', l)
    x_measured: np.ndarray  # (runs, T', k)
    excluded: np.ndarray  # (runs, T') bool
    dt: float

    def take(self, runs: np.ndarray) -> "Prepared":
        """The runs at the given indices."""
        fields = ("x", "xd", "xdd", "u", "q", "u_hold", "x_measured", "excluded")
        return dataclasses.replace(self, **{name: getattr(self, name)[runs] for name in fields})

    def arrays(self) -> tuple[jax.Array, ...]:
        """`(x, xd, u, q)` as JAX arrays: what the weak form evaluates."""
        return tuple(jnp.asarray(a) for a in (self.x, self.xd, self.u, self.q))


@eqx.filter_jit
def _joint_positions(coordinates, x):
    if not coordinates:
        return jnp.zeros(x.shape[:2] + (0,), dtype=x.dtype)
    return jax.vmap(jax.vmap(lambda y: jnp.stack([c(y) for c in coordinates])))(x)


def joint_positions(coordinates: tuple[AbstractCoordinate, ...], x: np.ndarray) -> np.ndarray:
    """The joint coordinates `(runs, T, m)` of positions `(runs, T, k)`, unwrapped along each run."""
    q = np.asarray(_joint_positions(tuple(coordinates), jnp.asarray(x)))
    return np.unwrap(q, axis=1) if q.size else q


def periodic_joints(joints: JointMap, x: ArrayLike) -> np.ndarray:
    """Which joints of a `JointMap` are angles: those a turn of `2 pi` maps to the same keypoints
    (tested at the configuration of keypoints `x`, `(k,)`). `(m,)` booleans."""
    q = joints.joints(jnp.asarray(x, dtype=float))
    base = joints.keypoints(q)
    turned = jax.vmap(lambda e: joints.keypoints(q + 2 * math.pi * e))(jnp.eye(joints.num_joints))
    tolerance = 1e-6 * (1.0 + float(jnp.max(jnp.abs(base))))
    return np.asarray(jnp.max(jnp.abs(turned - base[None]), axis=1) <= tolerance)


@eqx.filter_jit
def _to_joints(joints, x):
    return jax.vmap(joints.joints)(x)


def unwrapped_joints(joints: JointMap, x: ArrayLike) -> np.ndarray:
    """The joint coordinates `(runs, T, m)` of `joints` at keypoints `x` `(runs, T, k)`, its angles
    (`periodic_joints`) unwrapped along each run."""
    x = np.asarray(x, dtype=float)
    runs, samples, k = x.shape
    q = np.asarray(_to_joints(joints, jnp.asarray(x.reshape(-1, k)))).reshape(runs, samples, -1)
    return np.where(periodic_joints(joints, x[0, 0]), np.unwrap(q, axis=1), q)


@eqx.filter_jit
def to_keypoints(joints, q, qd):
    """Positions and velocities of the keypoints, `F(q)` and `DF(q) qd`, for joints `q`, `qd` `(n, m)`."""
    return jax.vmap(lambda a, b: jax.jvp(joints.keypoints, (a,), (b,)))(q, qd)


@eqx.filter_jit
def _to_keypoints(joints, q, qd, qdd):
    def one(q, qd, qdd):
        velocity = lambda a, b: jax.jvp(joints.keypoints, (a,), (b,))[1]  # noqa: E731
        x, xd = jax.jvp(joints.keypoints, (q,), (qd,))
        return x, xd, jax.jvp(velocity, (q, qd), (qd, qdd))[1]  # DF qdd + D2F[qd, qd]

    return jax.vmap(one)(q, qd, qdd)


def smooth_in_joints(
    choice: SmoothingChoice, joints: JointMap, x: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`choice.smooth` done on the joint coordinates of `joints` (angles unwrapped along each run) and
    mapped to the keypoints: `x = F(q)`, `xd = DF(q) qd`, `xdd = DF(q) qdd + D2F(q)[qd, qd]`.

    A polynomial in time holds a joint angle over the window where it cannot hold the arc that a
    keypoint traces on a link turning fast (a third of a radian per sample or more); the result also
    keeps the constraints exactly.

    **Returns:** three arrays of shape `(runs, len(choice.grid(T)), k)`.
    """
    x = np.asarray(x, dtype=float)
    runs, _, k = x.shape
    q = unwrapped_joints(joints, x)
    m = q.shape[-1]
    smoothed = (jnp.asarray(a.reshape(-1, m)) for a in choice.smooth(q))
    return tuple(np.asarray(a).reshape(runs, -1, k) for a in _to_keypoints(joints, *smoothed))


def _block_means(u: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """Means of `u` `(runs, T, l)` over `[start, start + length)` for each start (clipped to the run)."""
    cumulative = np.concatenate([np.zeros_like(u[:, :1]), np.cumsum(u, axis=1)], axis=1)
    lo = np.clip(starts, 0, u.shape[1])
    hi = np.clip(starts + length, 1, u.shape[1])
    lo = np.minimum(lo, hi - 1)
    return (cumulative[:, hi] - cumulative[:, lo]) / (hi - lo)[None, :, None]


def prepare(
    x: np.ndarray,
    u: np.ndarray,
    choice: SmoothingChoice,
    coordinates: tuple[AbstractCoordinate, ...],
    joints: JointMap | None = None,
) -> Prepared:
    """Smooth the runs, keep every `choice.step`-th sample, and compute their unwrapped joint
    coordinates.

    **Arguments:**

    - `x`: measured positions `(runs, T, k)`; `u`: controls `(runs, T, l)`, each held until the next
      sample.
    - `choice`: the `SmoothingChoice`; `coordinates`: the joint coordinates.
    - `joints`: a `JointMap` to smooth in its joint coordinates (`smooth_in_joints`); `None` smooths
      the keypoints.
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    xs, xds, xdds = choice.smooth(x) if joints is None else smooth_in_joints(choice, joints, x)
    grid = choice.grid(x.shape[1])
    step = choice.step
    q = joint_positions(tuple(coordinates), xs)
    return Prepared(
        x=xs,
        xd=xds,
        xdd=xdds,
        u=_block_means(u, grid - step // 2, step) if step > 1 else u[:, grid],
        q=q,
        u_hold=_block_means(u, grid, step) if step > 1 else u[:, grid],
        x_measured=x[:, grid],
        excluded=np.zeros(xs.shape[:2], dtype=bool),
        dt=choice.interval,
    )
