"""Smoothing settings from the data: the position noise, the motion's time scale, the Savitzky-Golay
window of least estimated velocity error, the test functions and the decimation (the criteria are
documented on `SmoothingChoice`)."""

import math

import numpy as np
from jaxtyping import ArrayLike

from .smoothing import Smoothing, SmoothingChoice, savitzky_golay

_DIFFERENCE_ORDERS = range(2, 7)
_MAD_TO_SIGMA = 1.0 / 0.6744897501960817  # median |N(0, 1)|
_WINDOW_RATIO = 1.25  # between candidate windows
_BIAS_REFERENCE = 1.6  # the bias of a window is estimated against one this much shorter
_TEST_PER_TIMESCALE = 2.0
_MIN_TEST_SAMPLES = 15  # a test function spans at least this many samples of the data
_TEST_PER_STRIDE = 6
_SAMPLES_PER_WINDOW = 10  # kept samples per smoothing window, at least
_SAMPLES_PER_TEST = 24  # kept samples per test function, at least
_NEGLIGIBLE_NOISE = 1e-4  # velocity noise below this fraction of the RMS velocity needs no resolving
_MAX_CENTRES = 400  # samples per run at which candidate windows are compared
_MAX_RUNS = 24


def estimate_noise(x: ArrayLike) -> float:
    """The standard deviation of white noise on sampled positions, estimated from the data alone.

    White noise of standard deviation $\\sigma$ gives `d`-th differences along a run of standard
    deviation $\\sigma \\sqrt{\\binom{2d}{d}}$, while a motion sampled finely enough adds little to
    them: the estimate is the median absolute `d`-th difference over $0.6745 \\sqrt{\\binom{2d}{d}}$
    (robust to the odd outlier), the smallest over `d = 2, ..., 6`. On noise-free data it is the
    small remainder of the motion itself.

    **Arguments:**

    - `x`: positions, shape `(runs, T, k)` (samples along axis 1).

    **Returns:** the estimated standard deviation, in the units of `x`.

    !!! example

        ```python
        sigma = cldyn.estimate_noise(data.x)   # about 0.001 for `cldyn record --noise 0.001`
        ```
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 3:
        raise ValueError(f"positions must have shape (runs, T, k), got {x.shape}")
    estimates = []
    for d in _DIFFERENCE_ORDERS:
        if x.shape[1] <= d:
            break
        differences = np.diff(x, n=d, axis=1)
        estimates.append(
            float(np.median(np.abs(differences))) * _MAD_TO_SIGMA / math.sqrt(math.comb(2 * d, d))
        )
    if not estimates:
        raise ValueError(f"runs of {x.shape[1]} samples are too short to estimate the noise")
    return min(estimates)


def _odd(n: float | int) -> int:
    n = int(round(n))
    return n if n % 2 else n + 1


def _windows(smallest: int, largest: int) -> list[int]:
    out = [smallest]
    while True:
        nxt = _odd(out[-1] * _WINDOW_RATIO)
        if nxt > largest:
            return out
        out.append(max(nxt, out[-1] + 2))


def _velocities(x: np.ndarray, window: int, order: int, centres: np.ndarray, dt: float):
    filters = savitzky_golay(window, order)
    half = window // 2
    index = centres[:, None] + np.arange(-half, half + 1)[None, :]
    windows = x[:, index, :]  # (runs, n, window, k)
    return np.einsum("rnwk,w->rnk", windows, filters[1]) / dt, np.einsum(
        "rnwk,w->rnk", windows, filters[2]
    ) / dt**2


def _padded(filter_: np.ndarray, window: int) -> np.ndarray:
    pad = (window - filter_.size) // 2
    return np.pad(filter_, (pad, pad))


def velocity_risks(x: np.ndarray, dt: float, order: int, noise: float, windows: list[int]):
    """The estimated mean-square velocity error of each candidate window (see `SmoothingChoice`), with
    the velocities and accelerations at the comparison samples. **Returns:** `(risks, estimates)`."""
    samples = x.shape[1]
    half = windows[-1] // 2
    centres = np.arange(half, samples - half, max(1, (samples - 2 * half) // _MAX_CENTRES))
    estimates = {w: _velocities(x, w, order, centres, dt) for w in windows}
    risks = []
    for w in windows:
        h1 = savitzky_golay(w, order)[1] / dt
        variance = noise**2 * float(np.sum(h1**2))
        shorter = [v for v in windows if v <= w / _BIAS_REFERENCE]
        bias2 = 0.0
        if shorter:
            reference = shorter[-1]
            ratio = w / reference
            h_ref = _padded(savitzky_golay(reference, order)[1] / dt, w)
            difference = estimates[w][0] - estimates[reference][0]
            excess = float(np.mean(difference**2)) - noise**2 * float(np.sum((h1 - h_ref) ** 2))
            bias2 = max(excess, 0.0) / (1.0 - ratio ** (-order)) ** 2
        risks.append(variance + bias2)
    return risks, estimates


def choose(smoothing: Smoothing, x: np.ndarray, dt: float) -> SmoothingChoice:
    """The `SmoothingChoice` for positions `x` `(runs, T, k)` sampled every `dt`: what `smoothing`
    gives, the rest chosen from the data."""
    if x.ndim != 3:
        raise ValueError(f"positions must have shape (runs, T, k), got {x.shape}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive sampling interval, got {dt}")
    order = smoothing.order
    samples = x.shape[1]
    smallest = _odd(order + 3)
    if samples < 2 * smallest:
        raise ValueError(
            f"runs of {samples} samples are too short for a smoothing window of {smallest} samples "
            f"(order {order}): identify needs at least {2 * smallest}"
        )
    sample = x[:: max(1, x.shape[0] // _MAX_RUNS)]
    noise = estimate_noise(x)
    chosen = {}
    if smoothing.window is not None:
        window = max(_odd(smoothing.window / dt), smallest)
        if window > samples // 2:
            raise ValueError(
                f"Smoothing: a window of {smoothing.window} s ({window} samples) is longer than half a run "
                f"({samples} samples of {dt} s)"
            )
        candidates = [window]
        chosen["window"] = "given"
    else:
        candidates = _windows(smallest, max(smallest, samples // 4))
        chosen["window"] = "least estimated velocity error (noise + bias)"
    risks, estimates = velocity_risks(sample, dt, order, noise, candidates)
    best = int(np.argmin(risks))
    window = candidates[best]
    velocity, acceleration = estimates[window]
    filters = savitzky_golay(window, order)
    v2 = float(np.mean(velocity**2)) - noise**2 * float(np.sum(filters[1] ** 2)) / dt**2
    a2 = float(np.mean(acceleration**2)) - noise**2 * float(np.sum(filters[2] ** 2)) / dt**4
    timescale = math.sqrt(max(v2, 0.0) / a2) if a2 > 0 else float("inf")

    interior = (samples - 2 * (window // 2)) * dt
    if smoothing.test_width is not None:
        test_seconds = smoothing.test_width
        chosen["test_width"] = "given"
    else:
        test_seconds = min(max(_TEST_PER_TIMESCALE * timescale, _MIN_TEST_SAMPLES * dt), interior / 3)
        chosen["test_width"] = "twice the motion's time scale (at least 15 samples, at most a third of a run)"
    step = 1
    if smoothing.decimate:
        # The kept samples must resolve the test functions (hence the motion) and, where noise passes
        # the smoothing in any measure, the smoothed noise too: coarser samples would alias it.
        target = test_seconds / _SAMPLES_PER_TEST
        noisy = noise**2 * float(np.sum(filters[1] ** 2)) / dt**2 > _NEGLIGIBLE_NOISE**2 * max(v2, 0.0)
        if noisy:
            target = min(target, window * dt / _SAMPLES_PER_WINDOW)
        step = max(1, int(target / dt + 1e-9))
        chosen["step"] = (
            "a kept sample every min(window / 10, test width / 24)"
            if noisy
            else "a kept sample every test width / 24 (the noise passing the smoothing is negligible)"
        )
    else:
        chosen["step"] = "given (no decimation)"
    interval = step * dt
    test_width = max(_odd(test_seconds / interval), 5)
    if smoothing.test_stride is not None:
        stride = max(1, int(round(smoothing.test_stride / interval)))
    else:
        stride = max(1, int(round(test_width / _TEST_PER_STRIDE)))
    stride = min(stride, test_width)
    return SmoothingChoice(
        dt=dt,
        window=window,
        order=order,
        step=step,
        test_width=test_width,
        test_stride=stride,
        noise=noise,
        timescale=timescale,
        velocity_error=math.sqrt(risks[best]),
        chosen=chosen,
    )
