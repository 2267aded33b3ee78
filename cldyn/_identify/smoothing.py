"""From measured positions to the data the weak form needs: smoothing differentiation, test
functions, and the prepared runs."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._coordinates import AbstractCoordinate


class Smoothing(eqx.Module):
    """How positions become the equations that identification regresses.

    Positions and velocities come from Savitzky-Golay smoothing differentiation: at every sample a
    polynomial of degree `order` is fitted by least squares to the `window` samples centred on it, and
    its value and derivatives there are the estimates (samples closer than `window // 2` to an end of
    a run are dropped). Accelerations are never needed by the regression: the equations of motion are
    integrated against smooth test functions $\\psi(t) = (1 - s^2)^4$ of `test_width` samples, placed
    every `test_stride` samples, and integration by parts moves the time derivative onto $\\psi$
    (the weak form). Second derivatives of measured positions are the weak point of direct residuals:
    at 100 Hz a fast acrobot's Savitzky-Golay accelerations carry a systematic error of several
    percent, enough to fake an inertia effect; the weak form removes it. The defaults suit 100 Hz data
    with position noise up to a millimetre. Smoothed accelerations are still computed, for the
    `accel_rmse` figure of the report.

    **Arguments:**

    - `window`: odd number of samples in each Savitzky-Golay fit.
    - `order`: its polynomial degree, at least 2 and less than `window`.
    - `test_width`: odd number of samples spanned by each test function.
    - `test_stride`: samples between the centres of consecutive test functions.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                smoothing=cldyn.Smoothing(window=15, order=6))
        ```
    """

    window: int = eqx.field(static=True, default=11)
    order: int = eqx.field(static=True, default=6)
    test_width: int = eqx.field(static=True, default=31)
    test_stride: int = eqx.field(static=True, default=5)

    def __check_init__(self):
        if self.window % 2 != 1 or self.window < 3:
            raise ValueError(f"window must be an odd number >= 3, got {self.window}")
        if not 2 <= self.order < self.window:
            raise ValueError(f"order must be in [2, window), got {self.order}")
        if self.test_width % 2 != 1 or self.test_width < 5 or not 1 <= self.test_stride <= self.test_width:
            raise ValueError(
                f"test_width must be odd and >= 5, and 1 <= test_stride <= test_width; got "
                f"{self.test_width}, {self.test_stride}"
            )

    @property
    def correlation(self) -> float:
        """Rows of the weak equations per independent one (test functions overlap)."""
        return self.test_width / self.test_stride

    @property
    def margin(self) -> int:
        """Samples lost at each end of a run."""
        return self.window // 2

    def coefficients(self, dt: float) -> np.ndarray:
        """The `(3, window)` filters for position, velocity and acceleration at the centre."""
        half = self.margin
        offsets = np.arange(-half, half + 1, dtype=float)
        vandermonde = offsets[:, None] ** np.arange(self.order + 1)[None, :]
        fit = np.linalg.pinv(vandermonde)  # (order + 1, window): polynomial coefficients
        return np.stack([fit[0], fit[1] / dt, 2.0 * fit[2] / dt**2])

    def __call__(self, x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Smoothed `(x, xd, xdd)` at the interior samples of each run.

        **Arguments:**

        - `x`: positions, shape `(runs, T, k)`.
        - `dt`: the sampling interval.

        **Returns:** three arrays of shape `(runs, T - 2 * margin, k)`.
        """
        x = np.asarray(x, dtype=float)
        if x.ndim != 3:
            raise ValueError(f"positions must have shape (runs, T, k), got {x.shape}")
        if x.shape[1] < self.window:
            raise ValueError(f"runs of {x.shape[1]} samples are shorter than the window {self.window}")
        windows = np.lib.stride_tricks.sliding_window_view(x, self.window, axis=1)
        filters = self.coefficients(dt)
        out = np.einsum("rtkw,dw->drtk", windows, filters)
        return out[0], out[1], out[2]

    def test_functions(self, samples: int, dt: float) -> "TestFunctions":
        """The test functions over runs of `samples` (interior) samples."""
        half = self.test_width // 2
        centres = np.arange(half, samples - half, self.test_stride)
        t = np.arange(samples)[None, :] - centres[:, None]
        s = t / (half + 1)
        inside = np.abs(s) < 1
        psi = np.where(inside, (1 - s**2) ** 4, 0.0)
        dpsi = np.where(inside, -8 * s * (1 - s**2) ** 3 / ((half + 1) * dt), 0.0)
        norm = psi.sum(axis=1, keepdims=True) * dt
        return TestFunctions(psi / norm * dt, dpsi / norm * dt)


@dataclasses.dataclass(frozen=True)
class TestFunctions:
    """Smooth bumps `psi_n(t)` with unit integral and their time derivatives, shape `(n, samples)`
    each, already multiplied by `dt` (the quadrature weight)."""

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


@dataclasses.dataclass(frozen=True)
class Prepared:
    """Smoothed runs: interior samples (`margin` dropped at each end) and the raw measurement."""

    x: np.ndarray  # (runs, T', k) smoothed, interior samples
    xd: np.ndarray
    xdd: np.ndarray
    u: np.ndarray  # (runs, T', l)
    q: np.ndarray  # (runs, T', m) unwrapped joint coordinates
    u_raw: np.ndarray  # (runs, T, l) all controls
    x_raw: np.ndarray  # (runs, T, k) all measured positions
    dt: float
    margin: int

    def take(self, runs: np.ndarray) -> "Prepared":
        """The runs at the given indices."""
        fields = ("x", "xd", "xdd", "u", "q", "u_raw", "x_raw")
        return dataclasses.replace(self, **{name: getattr(self, name)[runs] for name in fields})

    def arrays(self) -> tuple[jax.Array, ...]:
        """`(x, xd, u, q)` as JAX arrays: what the weak form evaluates."""
        return tuple(jnp.asarray(a) for a in (self.x, self.xd, self.u, self.q))


@eqx.filter_jit
def _joint_positions(coordinates, x):
    if not coordinates:
        return jnp.zeros(x.shape[:2] + (0,), dtype=x.dtype)
    return jax.vmap(jax.vmap(lambda y: jnp.stack([c(y) for c in coordinates])))(x)


def prepare(
    x: np.ndarray, u: np.ndarray, dt: float, smoothing: Smoothing, coordinates: tuple[AbstractCoordinate, ...]
) -> Prepared:
    """Smooth the runs and compute their unwrapped joint coordinates.

    **Arguments:**

    - `x`: measured positions `(runs, T, k)`; `u`: controls `(runs, T, l)`; `dt`: the interval.
    - `smoothing`: the `Smoothing`; `coordinates`: the joint coordinates.
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    samples = x.shape[1]
    xs, xds, xdds = smoothing(x, dt)
    m = smoothing.margin
    q = np.asarray(_joint_positions(tuple(coordinates), jnp.asarray(xs)))
    q = np.unwrap(q, axis=1) if q.size else q
    return Prepared(xs, xds, xdds, u[:, m : samples - m], q, u, x, float(dt), m)
