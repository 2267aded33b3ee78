"""The energy balance: joint damping that no error of a model's inertia or potential can fake.

Along a run, energy changes only by the work of the controls and of the dissipation. Over any window
`[a, b]` of a run, with the model's energy `E` and its known power `P` (controls, and the model's own
dissipative terms),

    E(b) - E(a) - int_a^b P dt = -sum_j c_j int_a^b qd_j^2 dt - (dE(b) - dE(a)),

where `c_j` is a viscous damping the model lacks at joint `j` and `dE(q, qd)` is the error of the
model's energy: a function of the configuration and quadratic in the velocities, whatever is wrong with
the model's inertia or potential. `dE` enters only at the window's two ends and never grows with the
window, where the dissipation does; written in a basis that holds any smooth energy of the joints, the
two separate. `cldyn.identify`'s force residual, in contrast, carries the model's conservative errors
at every sample: where those are larger than the damping's force (a model learnt from images), it cannot
see the damping, and the balance can.

Noise in the velocities makes the fit's columns noisy, which biases least squares (errors in variables).
With `instrumented`, every velocity is estimated three times from disjoint samples of the smoothing
window (offsets 0, 1 and 2 modulo 3), whose noises are independent where the positions' noise is white;
the columns and the energy are made of products of the first two (their noise averages out of a
product) and the instruments of the third.

A polynomial in time holds a joint angle over the smoothing window far better than the sines and cosines
that a keypoint on a fast-turning link traces: where a link turns a third of a radian or more per
sample, a window of eleven samples spans half a turn or more, the polynomial through the keypoints
misses their velocity, the more so the faster the turn, and the energy balance reads the error, which
grows with the speed, as dissipation. Given the mechanism's `JointMap`, the smoothing is done on its
joint coordinates (unwrapped) and mapped to the keypoints, `x = F(q)`, `xd = DF(q) qd`.
"""

import dataclasses
import itertools
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._coordinates import AbstractCoordinate, HingeAngle, JointMap
from .._data import Sequences
from .._system import ConstrainedLagrangian
from .smoothing import Smoothing, savitzky_golay, to_keypoints, unwrapped_joints

_MAX_ENDPOINTS = 40  # window ends per run: the number of windows must not grow with the sampling rate


@dataclasses.dataclass(frozen=True)
class EnergyBalance:
    """What `cldyn.energy_balance` found: the viscous damping each joint has beyond the model's own.

    **Fields:**

    - `joint_names`: the joints, in the order of `damping`.
    - `damping`: `(m,)` damping coefficients, in the model's energy unit times seconds per squared unit
      of the joint coordinate (N m s for a hinge of a model in SI units, N s/m for a slider).
    - `interval`: `(m, 2)` 95% intervals, percentiles of a bootstrap over whole runs.
    - `instrumented`: whether the fit was by instrumental variables (else least squares).
    - `window`, `order`: the Savitzky-Golay window (samples) and degree of the velocities.
    - `basis_order`: the order of the basis of the energy's error.
    - `joint_space`: whether the velocities were smoothed in joint coordinates (a `JointMap` was given).
    - `windows`: the number of balance windows fitted; `columns`: the number of unknowns.
    - `residual_rms`, `balance_rms`: RMS of the balance before and after the fit (energy units).
    """

    joint_names: tuple[str, ...]
    damping: np.ndarray
    interval: np.ndarray
    instrumented: bool
    window: int
    order: int
    basis_order: int
    joint_space: bool
    windows: int
    columns: int
    residual_rms: float
    balance_rms: float

    @property
    def detected(self) -> tuple[str, ...]:
        """The joints whose interval lies above zero."""
        return tuple(n for n, (low, _) in zip(self.joint_names, self.interval) if low > 0)

    def summary(self) -> str:
        """One line per joint: the damping and its interval."""
        fit = "instrumental variables" if self.instrumented else "least squares"
        space = "joint" if self.joint_space else "keypoint"
        lines = [
            f"energy balance ({fit}, window {self.window}, degree {self.order} in {space} coordinates, "
            f"{self.windows} windows):"
        ]
        for name, value, (low, high) in zip(self.joint_names, self.damping, self.interval):
            lines.append(f"  {name}: damping {value:.4g} [{low:.4g}, {high:.4g}]")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dictionary of the fields."""
        out = dataclasses.asdict(self)
        out["joint_names"] = list(self.joint_names)
        out["damping"] = [float(v) for v in self.damping]
        out["interval"] = [[float(a), float(b)] for a, b in self.interval]
        out["detected"] = list(self.detected)
        return out


def _disjoint(x: np.ndarray, window: int, order: int, dt: float) -> list[np.ndarray]:
    """Three velocity estimates `(runs, T - window + 1, k)` at the centres of every window: each the
    derivative of a polynomial through the samples at offsets `0, 1, 2` modulo 3 of the window."""
    half = window // 2
    offsets = np.arange(-half, half + 1)
    views = np.lib.stride_tricks.sliding_window_view(x, window, axis=1)  # (runs, n, k, window)
    out = []
    for remainder in range(3):
        chosen = offsets[offsets % 3 == remainder]
        scaled = chosen / max(half, 1)
        powers = scaled[:, None] ** np.arange(min(order, chosen.size - 1) + 1)
        weights = np.zeros(window)
        weights[chosen + half] = np.linalg.pinv(powers)[1] / max(half, 1) / dt
        out.append(np.einsum("rnkw,w->rnk", views, weights))
    return out


def _smoothed(x: np.ndarray, window: int, order: int, dt: float, instrumented: bool):
    """The smoothed positions `(runs, T - window + 1, k)` and three velocity estimates: from disjoint
    samples of the window (`instrumented`), else the one Savitzky-Golay derivative three times."""
    views = np.lib.stride_tricks.sliding_window_view(x, window, axis=1)
    filters = savitzky_golay(window, order)
    smooth = np.einsum("rnkw,w->rnk", views, filters[0])
    if instrumented:
        return (smooth, *_disjoint(x, window, order, dt))
    velocity = np.einsum("rnkw,w->rnk", views, filters[1] / dt)
    return smooth, velocity, velocity, velocity


def _features(q: np.ndarray, hinges: tuple[bool, ...], order: int) -> np.ndarray:
    """`(N, F)` products of one function per joint with total degree at most `order`: `cos`, `sin` of
    `d` times a hinge's angle, the Legendre polynomial of degree `d` of a slider scaled to `[-1, 1]`.
    Together they hold any smooth function of the joints to that order (the first column is 1)."""
    per_joint = []
    for j, hinge in enumerate(hinges):
        column = q[:, j]
        terms = [(0, np.ones_like(column))]
        if hinge:
            for d in range(1, order + 1):
                terms += [(d, np.cos(d * column)), (d, np.sin(d * column))]
        else:
            low, high = column.min(), column.max()
            s = (2 * column - low - high) / max(high - low, 1e-12)
            for d in range(1, order + 1):
                terms.append((d, np.polynomial.legendre.legval(s, [0] * d + [1])))
        per_joint.append(terms)
    columns = []
    for combination in itertools.product(*per_joint):
        if sum(d for d, _ in combination) <= order:
            columns.append(np.prod([f for _, f in combination], axis=0))
    return np.stack(columns, -1)


def _cumulative(f: np.ndarray, dt: float) -> np.ndarray:
    """`int_0^t f` along axis 1 at every sample: the trapezoid rule with the Euler-Maclaurin end
    correction, fourth order for smooth `f`."""
    trapezoid = np.concatenate(
        [np.zeros_like(f[:, :1]), np.cumsum((f[:, 1:] + f[:, :-1]) * dt / 2, axis=1)], 1
    )
    slope = np.gradient(f, dt, axis=1)
    return trapezoid - dt**2 / 12 * (slope - slope[:, :1])


def _held_work(flow: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """`int_0^t u^T g dt` at every sample, `u` held from each sample to the next (`flow` is `g = B^T xd`,
    `(runs, T, l)`): each interval's integral of `g` by the corrected trapezoid, times its control."""
    slope = np.gradient(flow, dt, axis=1)
    pieces = (flow[:, 1:] + flow[:, :-1]) * dt / 2 - dt**2 / 12 * (slope[:, 1:] - slope[:, :-1])
    work = np.einsum("rtl,rtl->rt", pieces, u[:, :-1])
    return np.concatenate([np.zeros_like(work[:, :1]), np.cumsum(work, axis=1)], 1)


def _model_terms(model: ConstrainedLagrangian, x, va, vb, u):
    """Per sample: the energy (kinetic energy polarised between the two velocity estimates), the input
    flow `B^T (va + vb) / 2` and the model's dissipation power (polarised, exact for linear forces)."""

    def one(p, a, b, c):
        kinetic = (model.kinetic_energy(p, a + b) - model.kinetic_energy(p, a - b)) / 4
        energy = model.potential_energy(p) + kinetic
        flow = jnp.zeros(c.shape, dtype=p.dtype)
        if model.input_matrix is not None and model.num_inputs > 0:
            flow = model.input_matrix(p).T @ ((a + b) / 2)
        power = jnp.zeros((), dtype=p.dtype)
        if model.dissipation is not None:
            power = (jnp.dot(a, model.dissipation(p, b)) + jnp.dot(b, model.dissipation(p, a))) / 2
        return energy, flow, power

    return jax.jit(jax.vmap(one))(x, va, vb, u)


def _rows(start: int, stop: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    points = np.unique(np.linspace(start, stop - 1, min(count, stop - start)).round().astype(int))
    first, last = np.triu_indices(len(points), 1)
    return points[first], points[last]


def _check(model, data, joint_coordinates, joints) -> None:
    if not isinstance(model, ConstrainedLagrangian):
        raise TypeError(f"energy_balance needs a ConstrainedLagrangian, got {type(model).__name__}")
    if not isinstance(data, Sequences):
        raise TypeError(f"energy_balance takes its data as a cldyn.Sequences, got {type(data).__name__}")
    if not joint_coordinates:
        raise ValueError("energy_balance needs at least one joint coordinate")
    for name, coordinate in joint_coordinates.items():
        if not isinstance(coordinate, AbstractCoordinate):
            raise TypeError(
                f"joint coordinate {name!r} is a {type(coordinate).__name__}, not a cldyn coordinate"
            )
    if data.size != model.size:
        raise ValueError(f"x must have shape (runs, T, {model.size}), got {tuple(data.x.shape)}")
    if data.num_inputs != model.num_inputs:
        raise ValueError(
            f"u must have {model.num_inputs} controls per sample, got shape {tuple(data.u.shape)}"
        )
    if joints is not None:
        if not isinstance(joints, JointMap):
            raise TypeError(f"joints must be a cldyn.JointMap, got {type(joints).__name__}")
        if tuple(joints.names) != tuple(joint_coordinates):
            raise ValueError(
                f"joints names its coordinates {tuple(joints.names)} but joint_coordinates has "
                f"{tuple(joint_coordinates)}: they must be the same joints in the same order"
            )
    if data.num_runs < 4:
        raise ValueError(f"energy_balance needs at least 4 runs (for its bootstrap), got {data.num_runs}")


def energy_balance(
    model: ConstrainedLagrangian,
    data: Sequences,
    *,
    joint_coordinates: Mapping[str, AbstractCoordinate],
    basis_order: int = 3,
    instrumented: bool = True,
    smoothing: Smoothing = Smoothing(),
    bootstrap: int = 200,
    seed: int = 0,
    joints: JointMap | None = None,
) -> EnergyBalance:
    """Measure the viscous damping at each joint that a model lacks, by an energy balance that errors
    of the model's inertia and potential cannot fake.

    Over every window `[a, b]` of every run, $E(b) - E(a) - \\int_a^b P\\,dt = -\\sum_j c_j \\int_a^b
    \\dot q_j^2\\,dt - \\Delta E(b) + \\Delta E(a)$, with `E` the model's energy, `P` the power of the
    controls and of the model's own dissipation, `c_j` the damping the model lacks at joint `j` and
    $\\Delta E$ the model's energy error, written in a basis of functions of the joints (Fourier terms of
    hinges, Legendre polynomials of sliders, products to total degree `basis_order`) for the potential and
    for each entry of the joint-space inertia. One fit over the windows of all runs; intervals from a
    bootstrap over whole runs. A check beside `cldyn.identify`, not a replacement: it sees only viscous
    joint damping, and sees it where the model's conservative errors hide it from the force residual.

    Velocities come from the Savitzky-Golay window and degree that `smoothing` chooses on the keypoints
    (as `identify` does). The window ends are spaced evenly, at most 40 per run, so the fit does not
    depend on the sampling rate. Controls are held from each sample to the next. With `joints`, the
    smoothing is done on the joint coordinates and mapped to the keypoints, which holds fast turns that
    a polynomial through the keypoints cannot (see the module's notes); the window is chosen on the
    keypoints either way.

    **Arguments:**

    - `model`: the nominal `ConstrainedLagrangian` (its energy, input matrix and dissipation are used).
    - `data`: the measured runs, a `cldyn.Sequences` (keypoints `x`, controls `u`, `dt`).
    - `joint_coordinates`: name -> joint coordinate; one per degree of freedom for the basis to hold
      every energy error.
    - `basis_order`: the total degree of the basis of the energy error.
    - `instrumented`: fit by instrumental variables (unbiased under white position noise) rather than
      least squares.
    - `smoothing`: how the velocities' window is chosen (`cldyn.Smoothing`).
    - `bootstrap`, `seed`: bootstrap replicates over runs, and their seed.
    - `joints`: the mechanism's `JointMap` (its names those of `joint_coordinates`, in order), to smooth
      in joint coordinates; `None` smooths the keypoints.

    **Returns:** an `EnergyBalance`.

    !!! example

        ```python
        hinge = cldyn.HingeAngle(child=(None, 0))
        balance = cldyn.energy_balance(model, data, joint_coordinates={"hinge": hinge})
        print(balance.summary())
        ```
    """
    _check(model, data, joint_coordinates, joints)
    if basis_order < 0:
        raise ValueError(f"basis_order must be non-negative, got {basis_order}")
    x = np.asarray(data.x, dtype=np.float64)
    u = np.asarray(data.u, dtype=np.float64)
    dt, (runs, samples, _) = float(data.dt), x.shape
    choice = smoothing.choose(x, dt)
    window, order = choice.window, choice.order
    if samples < window + 3:
        raise ValueError(
            f"runs of {samples} samples are too short for the smoothing window of {window} samples"
        )
    half, inner = window // 2, samples - window + 1
    flat = lambda a: jnp.asarray(a.reshape(-1, a.shape[-1]))  # noqa: E731
    coordinates = tuple(joint_coordinates.values())
    hinges = tuple(isinstance(c, HingeAngle) for c in coordinates)
    if joints is None:
        smooth, va, vb, vc = _smoothed(x, window, order, dt, instrumented)
    else:
        angles = unwrapped_joints(joints, x)
        q_smooth, *q_velocities = _smoothed(angles, window, order, dt, instrumented)
        mapped = [to_keypoints(joints, flat(q_smooth), flat(v)) for v in q_velocities]
        smooth = np.asarray(mapped[0][0]).reshape(runs, inner, -1)
        va, vb, vc = (np.asarray(tangent).reshape(runs, inner, -1) for _, tangent in mapped)
    held = u[:, half : half + inner]
    energy, flow, power = (
        np.asarray(a).reshape(runs, inner, *a.shape[1:])
        for a in _model_terms(model, flat(smooth), flat(va), flat(vb), flat(held))
    )
    work = _held_work(flow, held, dt) + _cumulative(power, dt)

    def joint_velocities(v):
        tangent = jax.vmap(lambda p, w: jnp.stack([jax.jvp(c, (p,), (w,))[1] for c in coordinates]))
        return np.asarray(tangent(flat(smooth), flat(v))).reshape(runs, inner, -1)

    q = np.asarray(jax.vmap(lambda p: jnp.stack([c(p) for c in coordinates]))(flat(smooth)))
    q = q.reshape(runs, inner, -1)
    q = np.where(np.array(hinges), np.unwrap(q, axis=1), q)
    features = _features(q.reshape(runs * inner, -1), hinges, basis_order).reshape(runs, inner, -1)
    qa, qb, qc = (joint_velocities(v) for v in (va, vb, vc))
    first, last = _rows(0, inner, _MAX_ENDPOINTS)

    def columns(a, b):
        m = a.shape[-1]
        basis = [features[..., 1:]]  # the potential's error (its constant drops out of every difference)
        for i, j in itertools.combinations_with_replacement(range(m), 2):
            product = (a[..., i] * b[..., j] + b[..., i] * a[..., j]) / 2
            basis.append(product[..., None] * features)
        basis = np.concatenate(basis, -1)
        dissipated = _cumulative(a * b, dt)
        return np.concatenate(
            [-(dissipated[:, last] - dissipated[:, first]), -(basis[:, last] - basis[:, first])], -1
        )

    a_columns = columns(qa, qb)
    z_columns = columns(qc, qc) if instrumented else a_columns
    y = energy[:, last] - energy[:, first] - (work[:, last] - work[:, first])
    scale = np.linalg.norm(a_columns.reshape(-1, a_columns.shape[-1]), axis=0) + 1e-300
    z_scale = np.linalg.norm(z_columns.reshape(-1, z_columns.shape[-1]), axis=0) + 1e-300
    a_n, z_n = a_columns / scale, z_columns / z_scale
    gram = np.einsum("rwi,rwj->rij", z_n, a_n)  # per run, so the bootstrap resamples sums
    moment = np.einsum("rwi,rw->ri", z_n, y)

    def solve(weights):
        matrix = np.einsum("r,rij->ij", weights, gram)
        rhs = np.einsum("r,ri->i", weights, moment)
        return np.linalg.lstsq(matrix, rhs, rcond=1e-12)[0] / scale

    theta = solve(np.ones(runs))
    rng = np.random.default_rng(seed)
    m = len(coordinates)
    draws = np.array(
        [
            solve(np.bincount(rng.integers(0, runs, runs), minlength=runs).astype(float))[:m]
            for _ in range(bootstrap)
        ]
    )
    residual = y - a_columns @ theta
    return EnergyBalance(
        joint_names=tuple(joint_coordinates),
        damping=theta[:m],
        interval=np.percentile(draws, [2.5, 97.5], axis=0).T,
        instrumented=instrumented,
        window=window,
        order=order,
        basis_order=basis_order,
        joint_space=joints is not None,
        windows=int(y.size),
        columns=int(a_columns.shape[-1]),
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        balance_rms=float(np.sqrt(np.mean(y**2))),
    )
