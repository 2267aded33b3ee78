"""Find the physics a model is missing: residual, attribution, augmentation, report.

The measured motion `x(t)` of a constrained mechanism obeys `M xdd = f(x, xd, u) + DPhi^T lambda + F`,
where `F` is whatever the model does not contain. The multipliers are unknown, but they act only
across the constraint manifold; along it, in the joint-space basis `G = dx/dq`,

    r = G^T (M xdd - f) = G^T F,

a generalised force per joint that the data determine. Every candidate effect (viscous damping,
Coulomb friction, a spring, rotor inertia, an actuator gain error, drag, a point mass) is a force linear
in its parameters, `F = sum_e theta_e phi_e(x, xd, xdd, u)`, so attribution is a sparse, sign-constrained
linear regression of `r` on the candidates' features `G^T phi_e`, with bootstrap over whole trajectories
for the uncertainty. Detected effects are added to the model as cldyn terms, the model is refitted, and
the loop repeats until nothing passes.
"""

import dataclasses
import itertools
import json
import math
import os
import pathlib
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from ._coordinates import AbstractCoordinate, JointMap
from ._dissipation import DissipationSum, JointCoulomb, JointDamping, KeypointDrag
from ._integrate import RK4, project_state, simulate
from ._mass import ConstantMass, JointArmature, PointMasses
from ._potential import Gravity, JointSpring, Sum
from ._system import ConstrainedLagrangian

EFFECTS = (
    "joint_damping",
    "joint_coulomb",
    "joint_spring",
    "joint_armature",
    "actuator_gain",
    "keypoint_drag",
    "point_mass",
)
"""The effect library, in the names used by reports."""

_GRAVITY = 9.81


# -- smoothing differentiation -----------------------------------------------------------------


class Smoothing(eqx.Module):
    """How positions become the equations that identification regresses.

    Positions and velocities come from Savitzky-Golay smoothing differentiation: at every sample a
    polynomial of degree `order` is fitted by least squares to the `window` samples centred on it, and
    its value and derivatives there are the estimates (samples closer than `window // 2` to an end of
    a run are dropped). Accelerations are never needed by the regression: the equations of motion are
    integrated against smooth test functions `psi(t) = (1 - s^2)^4` of `test_width` samples, placed
    every `test_stride` samples, and integration by parts moves the time derivative onto `psi`
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


# -- the effect library -------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One candidate effect at one place: a group of regression columns.

    **Fields:**

    - `effect`: one of `EFFECTS`.
    - `where`: the joint, actuator or keypoint name.
    - `index`: the joint, actuator column or keypoint index.
    - `kind`: a variant (`"linear"` or `"quadratic"` drag), else empty.
    - `columns`: the parameter names of its columns.
    - `signs`: per column, `+1` if physics demands a non-negative value, `0` if free.
    """

    effect: str
    where: str
    index: int
    kind: str = ""
    columns: tuple[str, ...] = ("value",)
    signs: tuple[int, ...] = (1,)

    @property
    def label(self) -> str:
        """A short name such as `joint_damping[shoulder]`."""
        kind = f"/{self.kind}" if self.kind else ""
        return f"{self.effect}{kind}[{self.where}]"

    def value(self, theta: np.ndarray) -> dict[str, float]:
        """The effect's parameters in MuJoCo's meaning and SI units, from its regression coefficients."""
        theta = np.asarray(theta, dtype=float)
        if self.effect == "joint_spring":
            stiffness = float(theta[0])
            rest = float(theta[1] / theta[0]) if stiffness != 0 else float("nan")
            return {"value": stiffness, "stiffness": stiffness, "springref": rest}
        if self.effect == "actuator_gain":
            return {"value": 1.0 + float(theta[0])}
        return {"value": float(theta[0])}


def _candidates(
    effects: Sequence[str],
    joint_names: Sequence[str],
    actuator_names: Sequence[str],
    keypoint_names: Sequence[str],
    gains: bool,
) -> list[Candidate]:
    out = []
    for effect in effects:
        if effect == "joint_damping":
            out += [Candidate(effect, n, j) for j, n in enumerate(joint_names)]
        elif effect == "joint_coulomb":
            out += [Candidate(effect, n, j) for j, n in enumerate(joint_names)]
        elif effect == "joint_spring":
            out += [
                Candidate(effect, n, j, columns=("stiffness", "stiffness*springref"), signs=(1, 0))
                for j, n in enumerate(joint_names)
            ]
        elif effect == "joint_armature":
            out += [Candidate(effect, n, j) for j, n in enumerate(joint_names)]
        elif effect == "actuator_gain":
            if gains:
                out += [
                    Candidate(effect, n, a, columns=("ratio-1",), signs=(0,))
                    for a, n in enumerate(actuator_names)
                ]
        elif effect == "keypoint_drag":
            for i, n in enumerate(keypoint_names):
                out += [Candidate(effect, n, i, kind="linear"), Candidate(effect, n, i, kind="quadratic")]
        elif effect == "point_mass":
            out += [Candidate(effect, n, i) for i, n in enumerate(keypoint_names)]
        else:
            raise ValueError(f"unknown effect {effect!r}; the library has {list(EFFECTS)}")
    return out


def _second_rate(coordinate: AbstractCoordinate, x, xd, xdd):
    """`qdd = grad q . xdd + xd^T D2q xd`, by two JVPs."""
    rate = lambda y: jax.jvp(coordinate, (y,), (xd,))[1]
    curvature = jax.jvp(rate, (x,), (xd,))[1]
    return jnp.dot(coordinate.gradient(x), xdd) + curvature


def _basis(model: ConstrainedLagrangian, joints: JointMap | None, x):
    """`G = dx/dq` (k, m) from the joint map, or an orthonormal basis of the tangent space."""
    if joints is not None:
        return jax.jacfwd(joints.keypoints)(joints.joints(x))
    jac = model.constraint.jacobian(x)
    _, _, vt = jnp.linalg.svd(jac, full_matrices=True)
    return vt[jac.shape[0] :].T


def _weak_pieces(joint_forces: Callable, x, xd, u, q):
    """The pieces of the weak form of `joint_forces(x, xd, xdd, u, q)`, without accelerations.

    Every column is `L(x) xdd + c(x, xd, u)`. With a test function `psi` that vanishes at both ends,
    integration by parts gives `int psi (L xdd + c) dt = int [-psi' (L xd) - psi (DL(x)[xd] xd) +
    psi c] dt`, so only positions and velocities are needed. Returns `(L xd, DL[xd] xd, c)`.
    """
    zero = jnp.zeros_like(xd)
    inertial = lambda y: joint_forces(y, xd, xd, u, q) - joint_forces(y, xd, zero, u, q)
    momentum, rate = jax.jvp(inertial, (x,), (xd,))
    return momentum, rate, joint_forces(x, xd, zero, u, q)


class _Residual(eqx.Module):
    """The joint-space residual `G^T (M xdd - f)` and inertial force `G^T M xdd`, shape `(m, 2)`."""

    model: ConstrainedLagrangian
    joints: JointMap | None

    def joint_forces(self, x, xd, xdd, u, q):
        basis = _basis(self.model, self.joints, x)
        residual = basis.T @ self.model.inverse_dynamics(x, xd, xdd, u)
        return jnp.stack([residual, basis.T @ self.model.mass.matvec(xdd)], axis=1)

    def __call__(self, x, xd, u, q):
        return _weak_pieces(self.joint_forces, x, xd, u, q)


class _Features(eqx.Module):
    """The joint-space force of every candidate column per unit parameter, shape `(m, C)`."""

    model: ConstrainedLagrangian
    coordinates: tuple[AbstractCoordinate, ...]
    joints: JointMap | None
    candidates: tuple[Candidate, ...] = eqx.field(static=True)
    velocity_scale: float = eqx.field(static=True)
    gravity: float = eqx.field(static=True)

    def forces(self, x, xd, xdd, u, q_unwrapped):
        """The Cartesian force of each candidate column per unit parameter, shape `(k, C)`."""
        k = x.shape[0]
        columns = []
        for c in self.candidates:
            if c.effect.startswith("joint_"):
                coordinate = self.coordinates[c.index]
                grad = coordinate.gradient(x)
                rate = jnp.dot(grad, xd)
                if c.effect == "joint_damping":
                    columns.append(-grad * rate)
                elif c.effect == "joint_coulomb":
                    columns.append(-grad * jnp.tanh(rate / self.velocity_scale))
                elif c.effect == "joint_spring":
                    columns += [-grad * q_unwrapped[c.index], grad]
                else:
                    columns.append(-grad * _second_rate(coordinate, x, xd, xdd))
            elif c.effect == "actuator_gain":
                columns.append(self.model.input_matrix(x)[:, c.index] * u[c.index])
            else:
                sl = slice(2 * c.index, 2 * c.index + 2)
                if c.effect == "keypoint_drag":
                    v = xd[sl]
                    value = -v if c.kind == "linear" else -jnp.sqrt(jnp.sum(v**2)) * v
                else:
                    value = -(xdd[sl] + jnp.array([0.0, self.gravity]))
                columns.append(jnp.zeros(k, dtype=x.dtype).at[sl].set(value))
        if not columns:
            return jnp.zeros((k, 0), dtype=x.dtype)
        return jnp.stack(columns, axis=1)

    def joint_forces(self, x, xd, xdd, u, q):
        return _basis(self.model, self.joints, x).T @ self.forces(x, xd, xdd, u, q)

    def __call__(self, x, xd, u, q):
        return _weak_pieces(self.joint_forces, x, xd, u, q)


@eqx.filter_jit
def _evaluate(pieces: _Residual | _Features, x, xd, u, q):
    return jax.vmap(jax.vmap(pieces))(x, xd, u, q)


def _test_functions(samples: int, width: int, stride: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth bumps `psi_k(t) = (1 - s^2)^4` of `width` samples, every `stride` samples, with unit
    integral, and their time derivatives; shape `(n, samples)` each, already multiplied by `dt` (the
    quadrature weight)."""
    half = width // 2
    centres = np.arange(half, samples - half, stride)
    t = np.arange(samples)[None, :] - centres[:, None]
    s = t / (half + 1)
    inside = np.abs(s) < 1
    psi = np.where(inside, (1 - s**2) ** 4, 0.0)
    dpsi = np.where(inside, -8 * s * (1 - s**2) ** 3 / ((half + 1) * dt), 0.0)
    norm = psi.sum(axis=1, keepdims=True) * dt
    return psi / norm * dt, dpsi / norm * dt


def _weak(pieces, psi: np.ndarray, dpsi: np.ndarray) -> np.ndarray:
    """Apply the test functions: `(runs, T, m, C) x 3 -> (runs, n, m, C)`."""
    momentum, rate, direct = (np.asarray(p) for p in pieces)
    return (
        -np.einsum("nt,rtmc->rnmc", dpsi, momentum)
        - np.einsum("nt,rtmc->rnmc", psi, rate)
        + np.einsum("nt,rtmc->rnmc", psi, direct)
    )


# -- sparse, sign-constrained regression on normal equations -------------------------------------


@dataclasses.dataclass(frozen=True)
class _Normal:
    """Sufficient statistics of weighted least squares: `A = Phi^T Phi`, `b = Phi^T r`, `c = r^T r`."""

    A: np.ndarray
    b: np.ndarray
    c: float
    n: int

    def __add__(self, other):
        return _Normal(self.A + other.A, self.b + other.b, self.c + other.c, self.n + other.n)


def _fit(normal: _Normal, columns: list[int], signs: list[int]) -> tuple[np.ndarray, float]:
    """Least squares on `columns` with `theta_i >= 0` where `signs[i] = 1`; returns (theta, RSS)."""
    if not columns:
        return np.zeros(0), normal.c
    idx = np.asarray(columns)
    A = normal.A[np.ix_(idx, idx)]
    b = normal.b[idx]
    constrained = [i for i, s in enumerate(signs) if s > 0]
    best = None
    # The optimum of a convex QP with bounds has some bounded variables at zero and the rest an
    # unconstrained optimum: try the active sets in order of size (the problems here are tiny).
    for size in range(len(constrained) + 1):
        for active in itertools.combinations(constrained, size):
            free = [i for i in range(len(idx)) if i not in active]
            theta = np.zeros(len(idx))
            if free:
                sub = A[np.ix_(free, free)]
                theta[free] = np.linalg.lstsq(sub, b[free], rcond=1e-12)[0]
            if any(theta[i] < 0 for i in constrained):
                continue
            rss = normal.c - 2 * theta @ b + theta @ A @ theta
            if best is None or rss < best[1] - 1e-12 * abs(normal.c):
                best = (theta, float(rss))
        if best is not None:
            break
    return best


def _bic(rss: float, n: int, p: int, correlation: float) -> float:
    n_eff = max(n / correlation, 2.0)
    return n_eff * math.log(max(rss, 1e-300) / n) + p * math.log(n_eff)


@dataclasses.dataclass(frozen=True)
class _Selection:
    groups: tuple[int, ...]
    theta: np.ndarray
    rss: float
    bic: float


def _group_columns(groups: Sequence[Sequence[int]], chosen, signs_of) -> tuple[list[int], list[int]]:
    columns = [c for g in chosen for c in groups[g]]
    return columns, [signs_of[c] for c in columns]


def _forward_select(
    normal: _Normal,
    groups: Sequence[Sequence[int]],
    signs: Sequence[int],
    correlation: float,
    min_gain: float,
    max_groups: int,
) -> _Selection:
    chosen: list[int] = []
    theta, rss = _fit(normal, [], [])
    bic = _bic(rss, normal.n, 0, correlation)
    while len(chosen) < max_groups:
        best = None
        for g in range(len(groups)):
            if g in chosen:
                continue
            columns, col_signs = _group_columns(groups, chosen + [g], signs)
            theta_g, rss_g = _fit(normal, columns, col_signs)
            own = theta_g[-len(groups[g]) :]
            own_signs = col_signs[-len(groups[g]) :]
            if any(s > 0 and t <= 0 for s, t in zip(own_signs, own)):
                continue  # the physically admissible fit does not use this candidate at all
            bic_g = _bic(rss_g, normal.n, len(columns), correlation)
            if best is None or bic_g < best[2]:
                best = (g, theta_g, bic_g, rss_g)
        if best is None or bic - best[2] < min_gain:
            break
        chosen.append(best[0])
        theta, bic, rss = best[1], best[2], best[3]
    return _Selection(tuple(chosen), theta, rss, bic)


# -- criteria and results -----------------------------------------------------------------------


class Criteria(eqx.Module):
    """When an effect counts as detected: every criterion must hold.

    **Arguments:**

    - `min_bic_gain`: removing the effect from the selected set must raise the Bayesian information
      criterion by at least this much (10 is "very strong" evidence). The BIC counts one independent
      sample per smoothing window, since smoothing correlates neighbouring residuals.
    - `min_t`: |estimate| / bootstrap standard error (the bootstrap resamples whole trajectories).
    - `min_inclusion`: the fraction of bootstrap replicates whose own selection includes the effect.
    - `min_holdout_drop`: the relative drop of the held-out residual sum of squares when the effect
      is added to the others.
    - `min_share`: the effect's generalised force, RMS, relative to the RMS of the inertial forces
      `G^T M xdd`: smaller effects do not matter to the motion and are not reported.
    """

    min_bic_gain: float = eqx.field(static=True, default=10.0)
    min_t: float = eqx.field(static=True, default=4.0)
    min_inclusion: float = eqx.field(static=True, default=0.9)
    min_holdout_drop: float = eqx.field(static=True, default=0.05)
    min_share: float = eqx.field(static=True, default=0.003)


@dataclasses.dataclass
class Detection:
    """An effect found in the data.

    **Fields:** `candidate`; `value` (MuJoCo meaning, SI units) and its bootstrap 95% interval `ci`;
    `parameters` (all of the effect's parameters); the evidence `bic_gain`, `t`, `inclusion`,
    `holdout_drop`, `share`; `alternatives`: candidates that the data cannot tell apart from it;
    `round`: the round of the loop that found it; `detected`: whether it passed every criterion.
    """

    candidate: Candidate
    value: float
    ci: tuple[float, float]
    parameters: dict[str, float]
    bic_gain: float
    t: float
    inclusion: float
    holdout_drop: float
    share: float
    alternatives: list[str]
    round: int
    detected: bool
    theta: np.ndarray = dataclasses.field(repr=False, default_factory=lambda: np.zeros(0))

    def to_dict(self) -> dict[str, Any]:
        """The report entry."""
        c = self.candidate
        out = {"effect": c.effect, "where": c.where, "value": self.value, "ci": list(self.ci)}
        if c.kind:
            out["kind"] = c.kind
        extra = {k: v for k, v in self.parameters.items() if k != "value"}
        if extra:
            out["parameters"] = extra
        out["evidence"] = {
            "bic_gain": self.bic_gain,
            "t": self.t,
            "bootstrap_inclusion": self.inclusion,
            "holdout_drop": self.holdout_drop,
            "share": self.share,
        }
        out["alternatives"] = self.alternatives
        out["round"] = self.round
        return out


# -- the data -----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Data:
    x: np.ndarray  # (runs, T', k) smoothed, interior samples
    xd: np.ndarray
    xdd: np.ndarray
    u: np.ndarray  # (runs, T', l)
    q: np.ndarray  # (runs, T', m) unwrapped joint coordinates
    raw: np.ndarray  # (runs, T', k) measured positions at the same samples
    u_raw: np.ndarray  # (runs, T, l) all controls
    x_raw: np.ndarray  # (runs, T, k) all measured positions
    dt: float
    margin: int

    def take(self, runs: np.ndarray) -> "_Data":
        pick = lambda a: a[runs]
        return dataclasses.replace(
            self,
            x=pick(self.x),
            xd=pick(self.xd),
            xdd=pick(self.xdd),
            u=pick(self.u),
            q=pick(self.q),
            raw=pick(self.raw),
            u_raw=pick(self.u_raw),
            x_raw=pick(self.x_raw),
        )


@eqx.filter_jit
def _joint_positions(coordinates, x):
    if not coordinates:
        return jnp.zeros(x.shape[:2] + (0,), dtype=x.dtype)
    return jax.vmap(jax.vmap(lambda y: jnp.stack([c(y) for c in coordinates])))(x)


def _prepare(x, u, dt, smoothing: Smoothing, coordinates) -> _Data:
    x = np.asarray(x, dtype=float)
    if x.ndim != 3:
        raise ValueError(f"x must have shape (runs, T, k), got {x.shape}")
    runs, samples, k = x.shape
    u = np.asarray(u, dtype=float)
    if u.ndim == 2:
        u = np.broadcast_to(u[:, None, :], (runs, samples, u.shape[1]))
    if u.ndim != 3 or u.shape[:2] != (runs, samples):
        raise ValueError(f"u must have shape (runs, T, l) or (runs, l) matching x {x.shape}, got {u.shape}")
    for name, a in (("x", x), ("u", u)):
        bad = ~np.isfinite(a)
        if bad.any():
            run, sample = np.argwhere(bad)[0][:2]
            raise ValueError(f"{name} contains NaN or infinite values (first at run {run}, sample {sample})")
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    xs, xds, xdds = smoothing(x, dt)
    m = smoothing.margin
    q = np.asarray(_joint_positions(tuple(coordinates), jnp.asarray(xs)))
    q = np.unwrap(q, axis=1) if q.size else q
    return _Data(xs, xds, xdds, u[:, m : samples - m], q, x[:, m : samples - m], u, x, float(dt), m)


# -- augmentation and refit ---------------------------------------------------------------------


def _add_potential(model: ConstrainedLagrangian, term) -> ConstrainedLagrangian:
    potential = term if model.potential is None else model.potential + term
    return eqx.tree_at(lambda s: s.potential, model, potential, is_leaf=lambda v: v is None)


def _add_dissipation(model: ConstrainedLagrangian, term) -> ConstrainedLagrangian:
    dissipation = term if model.dissipation is None else model.dissipation + term
    if not isinstance(dissipation, DissipationSum):
        dissipation = DissipationSum([dissipation])
    return eqx.tree_at(lambda s: s.dissipation, model, dissipation, is_leaf=lambda v: v is None)


def _gravity_of(model: ConstrainedLagrangian) -> float:
    terms = model.potential.terms if isinstance(model.potential, Sum) else (model.potential,)
    for t in terms:
        if isinstance(t, Gravity):
            return float(t.g)
    return _GRAVITY


def augment(
    model: ConstrainedLagrangian,
    detections: Sequence[Detection],
    coordinates: Sequence[AbstractCoordinate],
    *,
    velocity_scale: float = 0.05,
) -> ConstrainedLagrangian:
    """Add detected effects to a model as cldyn terms, at their estimated values.

    **Arguments:**

    - `model`: the model to extend.
    - `detections`: the effects (as returned by `identify`).
    - `coordinates`: the joint coordinates that joint effects act through, indexed as in the
      candidates.
    - `velocity_scale`: the smoothing speed of Coulomb friction (`JointCoulomb`).

    **Returns:** the augmented `ConstrainedLagrangian`.
    """
    for d in detections:
        c, theta = d.candidate, np.asarray(d.theta, dtype=float)
        if c.effect == "joint_damping":
            model = _add_dissipation(model, JointDamping([coordinates[c.index]], theta[0]))
        elif c.effect == "joint_coulomb":
            term = JointCoulomb([coordinates[c.index]], theta[0], velocity_scale=velocity_scale)
            model = _add_dissipation(model, term)
        elif c.effect == "joint_spring":
            rest = theta[1] / theta[0]
            term = JointSpring(coordinates[c.index], stiffness=theta[0], rest=rest, periodic=True)
            model = _add_potential(model, term)
        elif c.effect == "joint_armature":
            if model.armature is None:
                armature = JointArmature([coordinates[c.index]], theta[0])
            else:
                armature = JointArmature(
                    model.armature.coordinates + (coordinates[c.index],),
                    jnp.concatenate([model.armature.armature, jnp.asarray(theta[:1])]),
                )
            model = eqx.tree_at(lambda s: s.armature, model, armature, is_leaf=lambda v: v is None)
        elif c.effect == "actuator_gain":
            gears = model.input_matrix.gears
            model = eqx.tree_at(
                lambda s: s.input_matrix.gears, model, gears.at[c.index].multiply(1.0 + theta[0])
            )
        elif c.effect == "keypoint_drag":
            n = model.size // 2
            linear = np.zeros(n)
            quadratic = np.zeros(n)
            (linear if c.kind == "linear" else quadratic)[c.index] = theta[0]
            model = _add_dissipation(model, KeypointDrag(jnp.asarray(linear), jnp.asarray(quadratic)))
        elif c.effect == "point_mass":
            model = _add_point_mass(model, c.index, float(theta[0]))
    return model


def _add_point_mass(model: ConstrainedLagrangian, keypoint: int, mass: float) -> ConstrainedLagrangian:
    sl = slice(2 * keypoint, 2 * keypoint + 2)
    if isinstance(model.mass, PointMasses):
        masses = model.mass.masses.at[keypoint].add(mass)
        new_mass = PointMasses(masses, dim=model.mass.dim)
    else:
        matrix = model.mass.matrix().at[sl, sl].add(mass * jnp.eye(2))
        new_mass = ConstantMass(matrix)
    weights = jnp.zeros(model.size).at[2 * keypoint + 1].set(mass)
    model = eqx.tree_at(lambda s: s.mass, model, new_mass)
    return _add_potential(model, Gravity(weights, _gravity_of(model)))


def _refit_filter(model: ConstrainedLagrangian):
    """Refit the potential, the dissipation and the armature; the mass matrix and the actuator gears
    stay put, since the equations of motion are homogeneous in (M, V, g, F): one of them must fix the
    scale."""
    spec = jax.tree_util.tree_map(lambda _: False, model)
    for where in (lambda s: s.potential, lambda s: s.dissipation, lambda s: s.armature):
        part = where(model)
        if part is None:
            continue
        spec = eqx.tree_at(
            where, spec, jax.tree_util.tree_map(eqx.is_inexact_array, part), is_leaf=lambda v: v is None
        )
    return spec


def refit(
    model: ConstrainedLagrangian,
    data: _Data,
    joints: JointMap | None,
    weights: np.ndarray,
    test_functions: tuple[np.ndarray, np.ndarray],
    *,
    max_steps: int | None = None,
) -> ConstrainedLagrangian:
    """Least-squares refit of the weighted weak joint-space residual (optimistix).

    Levenberg-Marquardt for parametric models; for larger ones (a neural potential), whose Jacobian
    would not fit in memory, BFGS on the sum of squares, which needs gradients only.
    """
    spec = _refit_filter(model)
    params, static = eqx.partition(model, spec)
    size = sum(leaf.size for leaf in jax.tree_util.tree_leaves(params))
    if size == 0:
        return model
    arrays = tuple(jnp.asarray(a) for a in (data.x, data.xd, data.u, data.q))
    tests = tuple(jnp.asarray(a) for a in test_functions)
    args = (static, joints, arrays, tests, jnp.asarray(weights))
    if size <= _LM_MAX_PARAMETERS:
        solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)
        steps = 30 if max_steps is None else max_steps
        solution = optx.least_squares(_weak_residual, solver, params, args, max_steps=steps, throw=False)
    else:
        solver = optx.BFGS(rtol=1e-8, atol=1e-10)
        steps = 500 if max_steps is None else max_steps
        solution = optx.minimise(_sum_of_squares, solver, params, args, max_steps=steps, throw=False)
    return eqx.combine(solution.value, static)


# Levenberg-Marquardt materialises the (residuals x parameters) Jacobian
_LM_MAX_PARAMETERS = 256


def _sum_of_squares(params, args):
    residual = _weak_residual(params, args)
    return 0.5 * jnp.sum(residual**2) / residual.shape[0]


def _weak_residual(params, args):
    static, joints, (x, xd, u, q), (psi, dpsi), weights = args
    pieces = jax.vmap(jax.vmap(_Residual(eqx.combine(params, static), joints)))(x, xd, u, q)
    momentum, rate, direct = (p[..., 0] for p in pieces)
    weak = (
        -jnp.einsum("nt,rtm->rnm", dpsi, momentum)
        - jnp.einsum("nt,rtm->rnm", psi, rate)
        + jnp.einsum("nt,rtm->rnm", psi, direct)
    )
    return (weak * weights[None, None, :]).reshape(-1)


# -- before/after metrics -----------------------------------------------------------------------


@eqx.filter_jit
def _accelerations(model, x, xd, u):
    return jax.vmap(jax.vmap(model.acceleration))(x, xd, u)


def _simulate_held(model, x0, xd0, us, ts):
    """One rollout: RK4, one step per sample, the recorded controls held per sample."""
    dt = ts[1] - ts[0]

    def control(t):
        index = jnp.clip(jnp.floor(t / dt + 1e-6).astype(int), 0, us.shape[0] - 1)
        return us[index]

    x0, xd0 = project_state(model, x0, xd0)
    control = control if model.num_inputs else None
    # forward mode: the initial-state fit differentiates through this with Jacobian-vector products
    return simulate(model, x0, xd0, ts, control=control, solver=RK4(), dt0=None, adjoint=dfx.ForwardMode()).x


@eqx.filter_jit
def _rollout_batch(model, x0, xd0, us, ts, measured, window: int):
    """Rollouts from the start of each run.

    The initial state is estimated with the model itself: starting from the smoothed state, the
    positions and velocities are adjusted (Gauss-Newton) so that the first `window` samples of
    the rollout match the measurement. This removes most of the measurement noise from the initial
    velocity, which otherwise dominates the rollout error of noisy data, for every model alike.
    """

    def one(x0, xd0, us, measured):
        def residual(delta, _):
            xs = _simulate_held(model, x0 + delta[0], xd0 + delta[1], us[: window + 1], ts[: window + 1])
            return (xs - measured[: window + 1]).reshape(-1)

        zero = (jnp.zeros_like(x0), jnp.zeros_like(xd0))
        # velocity changes across the constraints are projected away: a rank-deficient problem
        solver = optx.GaussNewton(rtol=1e-6, atol=1e-9, linear_solver=lx.SVD(rcond=1e-8))
        delta = optx.least_squares(residual, solver, zero, max_steps=20, throw=False).value
        return _simulate_held(model, x0 + delta[0], xd0 + delta[1], us, ts)

    return jax.vmap(one)(x0, xd0, us, measured)


def _rollouts(
    model: ConstrainedLagrangian, data: _Data, horizon: float, window: float = 0.2
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint position error over time of rollouts from the first interior state of every run."""
    steps = min(int(round(horizon / data.dt)), data.x.shape[1] - 1)
    ts = np.arange(steps + 1) * data.dt
    start = data.margin
    us = data.u_raw[:, start : start + steps + 1]
    if model.num_inputs == 0:
        us = np.zeros(us.shape[:2] + (1,))
    measured = data.x_raw[:, start : start + steps + 1]
    samples = max(2, min(steps, int(round(window / data.dt))))
    xs = _rollout_batch(
        model,
        jnp.asarray(data.x[:, 0]),
        jnp.asarray(data.xd[:, 0]),
        jnp.asarray(us),
        ts,
        jnp.asarray(measured),
        samples,
    )
    error = np.linalg.norm((np.asarray(xs) - measured).reshape(xs.shape[0], steps + 1, -1, 2), axis=-1)
    return ts, error


def _metrics(
    model, data: _Data, horizon: float, tests: tuple[np.ndarray, np.ndarray]
) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
    acc = np.asarray(_accelerations(model, jnp.asarray(data.x), jnp.asarray(data.xd), jnp.asarray(data.u)))
    # the acceleration error averaged over each test function, int psi (xdd_model - xdd) dt, with
    # int psi xdd dt = -int psi' xd dt: no second differences of the measurement
    psi, dpsi = tests
    error = np.einsum("nt,rtk->rnk", psi, acc) + np.einsum("nt,rtk->rnk", dpsi, data.xd)
    accel_rmse = float(np.sqrt(np.mean(error**2)))
    ts, error = _rollouts(model, data, horizon)
    rollout_rmse = float(np.sqrt(np.mean(error**2)))
    return {"accel_rmse": accel_rmse, "rollout_rmse_1s": rollout_rmse, "horizon": float(ts[-1])}, ts, error


# -- the loop -----------------------------------------------------------------------------------


@dataclasses.dataclass
class Identification:
    """The outcome of `identify`: what was found, the model with it, and the errors before and after.

    **Fields:**

    - `detected`: the `Detection`s that passed every criterion, strongest first in each round.
    - `rejected`: the candidates that were selected but failed a criterion (for the record).
    - `before`, `after`: `accel_rmse` (m/s^2: the model's keypoint accelerations on held-out runs
      against the measured ones, both averaged over the test functions, so that no second difference of
      noisy positions is involved) and `rollout_rmse_1s` (m, keypoint positions over one-second rollouts from
      the start of each held-out run, against the measurement; each model estimates its own initial
      state from the first 0.2 s of the run, by Gauss-Newton on its rollout, so that measurement noise
      in the initial velocity does not swamp the comparison).
    - `model`: the augmented, refitted `ConstrainedLagrangian`; `nominal`: the model it started from.
    - `settings`: everything needed to reproduce the run.
    """

    detected: list[Detection]
    rejected: list[Detection]
    before: dict[str, float]
    after: dict[str, float]
    model: ConstrainedLagrangian
    nominal: ConstrainedLagrangian
    settings: dict[str, Any]
    rounds: list[dict[str, Any]]
    curves: dict[str, np.ndarray] = dataclasses.field(repr=False)
    scatter: list[dict[str, Any]] = dataclasses.field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """The content of `report.json`."""
        return {
            "detected": [d.to_dict() for d in self.detected],
            "before": self.before,
            "after": self.after,
            "improvement": {
                k: (self.before[k] / self.after[k] if self.after[k] > 0 else float("inf"))
                for k in ("accel_rmse", "rollout_rmse_1s")
            },
            "rejected": [d.to_dict() for d in self.rejected],
            "rounds": self.rounds,
            "settings": self.settings,
        }

    def summary(self) -> str:
        """A few human-readable lines."""
        lines = []
        if not self.detected:
            lines.append("no missing effect detected")
        for d in self.detected:
            c = d.candidate
            alt = f" (or: {', '.join(d.alternatives)})" if d.alternatives else ""
            lines.append(
                f"detected {c.effect}{'/' + c.kind if c.kind else ''} at {c.where}: {d.value:.4g} "
                f"[{d.ci[0]:.4g}, {d.ci[1]:.4g}]{alt}"
            )
        for key, unit in (("accel_rmse", "m/s^2"), ("rollout_rmse_1s", "m")):
            b, a = self.before[key], self.after[key]
            lines.append(f"{key}: {b:.4g} -> {a:.4g} {unit} ({b / a:.1f}x)" if a > 0 else f"{key}: {b:.4g}")
        return "\n".join(lines)

    def save(self, directory: "str | os.PathLike") -> pathlib.Path:
        """Write `report.json`, `report.md` and the plots into `directory` (created if needed)."""
        directory = pathlib.Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        report = self.to_dict()
        _atomic_write(directory / "report.json", json.dumps(report, indent=2, default=_json_default))
        _atomic_write(directory / "report.md", _markdown(report, self))
        _plots(self, directory)
        return directory


def _json_default(value):
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _atomic_write(path: pathlib.Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def identify(
    model: ConstrainedLagrangian,
    x: Float[Array, "runs T k"] | np.ndarray,
    u: np.ndarray | None,
    dt: float,
    *,
    joint_coordinates: Mapping[str, AbstractCoordinate],
    joints: JointMap | None = None,
    actuator_names: Sequence[str] | None = None,
    keypoint_names: Sequence[str] | None = None,
    effects: Sequence[str] = EFFECTS,
    smoothing: Smoothing = Smoothing(),
    criteria: Criteria = Criteria(),
    holdout: float = 0.25,
    bootstrap: int = 100,
    max_rounds: int = 3,
    max_effects: int = 4,
    velocity_scale: float = 0.05,
    horizon: float = 1.0,
    seed: int = 0,
    progress: bool = False,
) -> Identification:
    """Find the effects that a model of a constrained mechanism is missing, add them, and refit.

    1. **Residual.** Positions are smoothed and differentiated (`Smoothing`); the joint-space residual
       `r = G^T (M(x) xdd - f(x, xd, u))` with `G = dx/dq` is what the model misses along the
       constraint manifold (the unknown multipliers drop out).
    2. **Attribution.** Every candidate of the effect library is a force linear in its parameters;
       a forward selection by the Bayesian information criterion with sign constraints picks a sparse
       set; a bootstrap over whole runs gives intervals, t-statistics and inclusion probabilities; the
       held-out runs check that each effect improves prediction. An effect is detected only when all
       `Criteria` hold. Candidates that explain the data about as well are reported as alternatives.
    3. **Augment and refit.** Detected effects become cldyn terms (`JointDamping`, `JointCoulomb`,
       `JointSpring`, `JointArmature`, a gear factor, `KeypointDrag`, a point mass); the potential and
       the dissipative terms are refitted by Levenberg-Marquardt; the loop repeats until nothing
       passes.
    4. **Report.** Errors before and after on held-out runs.

    **Arguments:**

    - `model`: the nominal `ConstrainedLagrangian` (analytic, from `from_mjcf`, or learned).
    - `x`: measured keypoint positions, shape `(runs, T, k)`, possibly noisy.
    - `u`: the controls, `(runs, T, l)` or `(runs, l)`; `None` for an uncontrolled system.
    - `dt`: the sampling interval.
    - `joint_coordinates`: name -> joint coordinate `q(x)`, for the joint effects (for a MuJoCo
      model: `dict(zip(bridge.joint_names, bridge.joint_coordinates))`).
    - `joints`: the `JointMap` whose Jacobian is the basis `G`; without it, an orthonormal basis of
      the tangent space.
    - `actuator_names`, `keypoint_names`: names for reports.
    - `effects`: which effects of `EFFECTS` to consider.
    - `smoothing`, `criteria`: see `Smoothing` and `Criteria`.
    - `holdout`: fraction of runs held out for checks and for the before/after errors.
    - `bootstrap`: bootstrap replicates.
    - `max_rounds`: rounds of detect-augment-refit.
    - `max_effects`: the most effects selected in one round.
    - `velocity_scale`: the smoothing speed of the Coulomb friction candidates (rad/s or m/s).
    - `horizon`: rollout length for `rollout_rmse_1s`.
    - `seed`: for the split and the bootstrap.
    - `progress`: print what each round does.

    **Returns:** an `Identification`; `.save(dir)` writes the report and the plots.
    """
    started = time.perf_counter()
    if not isinstance(model, ConstrainedLagrangian) or model.num_constraints == 0:
        raise TypeError("identify needs a ConstrainedLagrangian with constraints")
    names = tuple(joint_coordinates)
    coordinates = tuple(joint_coordinates[n] for n in names)
    if joints is not None and joints.num_joints != len(coordinates):
        raise ValueError(
            f"joints has {joints.num_joints} joint coordinates but joint_coordinates has {len(coordinates)}"
        )
    x = np.asarray(x, dtype=float)
    if x.ndim != 3 or x.shape[2] != model.size:
        raise ValueError(f"x must have shape (runs, T, {model.size}), got {x.shape}")
    if u is None:
        u = np.zeros(x.shape[:2] + (model.num_inputs,))
    u = np.asarray(u, dtype=float)
    if u.shape[-1] != model.num_inputs:
        raise ValueError(f"u must have {model.num_inputs} controls per sample, got shape {u.shape}")
    runs = x.shape[0]
    if runs < 4:
        raise ValueError(f"identify needs at least 4 runs (for held-out checks and bootstrap), got {runs}")
    actuator_names = tuple(actuator_names or (f"u{a}" for a in range(model.num_inputs)))
    keypoint_names = tuple(keypoint_names or (f"keypoint{i}" for i in range(model.size // 2)))
    log = print if progress else (lambda *a, **k: None)

    data = _prepare(x, u, dt, smoothing, coordinates)
    rng = np.random.default_rng(seed)
    order = rng.permutation(runs)
    n_hold = max(1, int(round(holdout * runs)))
    held, fit_runs = np.sort(order[:n_hold]), np.sort(order[n_hold:])
    fit_data, held_data = data.take(fit_runs), data.take(held)

    gains = model.input_matrix is not None and hasattr(model.input_matrix, "gears") and model.num_inputs > 0
    all_candidates = _candidates(effects, names, actuator_names, keypoint_names, gains)
    gravity = _gravity_of(model) if model.potential is not None else _GRAVITY

    def features_for(current, candidates):
        return _Features(current, coordinates, joints, tuple(candidates), velocity_scale, gravity)

    offsets = np.cumsum([0] + [len(c.columns) for c in all_candidates])

    tests = _test_functions(data.x.shape[1], smoothing.test_width, smoothing.test_stride, data.dt)
    if tests[0].shape[0] == 0:
        raise ValueError(
            f"runs of {x.shape[1]} samples are too short for the smoothing window {smoothing.window} and "
            f"test functions of {smoothing.test_width} samples"
        )

    log(f"identify: {runs} runs ({len(fit_runs)} fit, {len(held)} held out), {data.x.shape[1]} samples each")
    before, ts, error_before = _metrics(model, held_data, horizon, tests)
    log(
        f"  before: accel_rmse {before['accel_rmse']:.4g} m/s^2, "
        f"rollout_rmse_1s {before['rollout_rmse_1s']:.4g} m"
    )

    current = model
    detected: list[Detection] = []
    rejected: list[Detection] = []
    rounds = []
    scatter = []
    used: set[str] = set()
    weights = None
    arrays = tuple(jnp.asarray(a) for a in (data.x, data.xd, data.u, data.q))
    # the candidates' features do not change from round to round: evaluate them once, on every run
    features = _weak(_evaluate(features_for(model, all_candidates), *arrays), *tests)
    for round_index in range(1, max_rounds + 1):
        active = [j for j, c in enumerate(all_candidates) if c.label not in used]
        if not active:
            break
        candidates = [all_candidates[j] for j in active]
        columns = [
            col for j in active for col in range(offsets[j], offsets[j] + len(all_candidates[j].columns))
        ]
        residual = _weak(_evaluate(_Residual(current, joints), *arrays), *tests)
        r_fit, inertial_fit = residual[fit_runs, ..., 0], residual[fit_runs, ..., 1]
        r_held = residual[held, ..., 0]
        f_fit, f_held = features[fit_runs][..., columns], features[held][..., columns]
        if weights is None:
            weights = 1.0 / np.maximum(r_fit.reshape(-1, r_fit.shape[-1]).std(axis=0), 1e-12)
        result = _attribute(
            candidates,
            r_fit,
            f_fit,
            inertial_fit,
            r_held,
            f_held,
            weights,
            smoothing,
            criteria,
            bootstrap,
            max_effects,
            rng,
            round_index,
        )
        rounds.append(result["summary"])
        new = [d for d in result["selected"] if d.detected]
        rejected += [d for d in result["selected"] if not d.detected]
        log(f"  round {round_index}: " + ("; ".join(d.candidate.label for d in new) or "nothing passes"))
        if not new:
            break
        for d in new:
            j = candidates.index(d.candidate)
            cols = result["columns"][j]
            scatter.append(
                {
                    "label": d.candidate.label,
                    "feature": f_held[..., cols] @ np.asarray(d.theta),
                    "residual": r_held,
                    "effect": d.candidate.effect,
                    "round": round_index,
                }
            )
        detected += new
        used |= {d.candidate.label for d in new}
        current = augment(current, new, coordinates, velocity_scale=velocity_scale)
        current = refit(current, fit_data, joints, weights, tests)
        for d in new:
            _update_from_model(d, current, coordinates)

    after, _, error_after = _metrics(current, held_data, horizon, tests)
    log(
        f"  after: accel_rmse {after['accel_rmse']:.4g} m/s^2, "
        f"rollout_rmse_1s {after['rollout_rmse_1s']:.4g} m"
    )
    settings = {
        "runs": runs,
        "fit_runs": fit_runs.tolist(),
        "held_out_runs": held.tolist(),
        "dt": float(dt),
        "smoothing": {
            "velocities": "savitzky-golay",
            "window": smoothing.window,
            "order": smoothing.order,
            "equations": "weak form, test functions (1 - s^2)^4",
            "test_width": smoothing.test_width,
            "test_stride": smoothing.test_stride,
        },
        "criteria": {
            f.name: getattr(criteria, f.name)
            for f in dataclasses.fields(criteria)  # type: ignore[arg-type]
        },
        "bootstrap": bootstrap,
        "effects": list(effects),
        "velocity_scale": velocity_scale,
        "seed": seed,
        "seconds": time.perf_counter() - started,
    }
    curves = {"ts": ts, "before": error_before, "after": error_after}
    return Identification(
        detected, rejected, before, after, current, model, settings, rounds, curves, scatter
    )


def _same(a, b) -> bool:
    return type(a) is type(b) and bool(eqx.tree_equal(a, b))


def _update_from_model(d: Detection, model: ConstrainedLagrangian, coordinates) -> None:
    """After the refit, report the refitted value; the bootstrap interval moves with it."""
    c = d.candidate
    refitted = None
    if c.effect in ("joint_damping", "joint_coulomb") and model.dissipation is not None:
        kind = JointDamping if c.effect == "joint_damping" else JointCoulomb
        for term in model.dissipation.terms:
            if isinstance(term, kind) and _same(term.coordinates[0], coordinates[c.index]):
                refitted = float((term.damping if kind is JointDamping else term.friction)[0])
    elif c.effect == "joint_spring":
        terms = model.potential.terms if isinstance(model.potential, Sum) else (model.potential,)
        for term in terms:
            if isinstance(term, JointSpring) and _same(term.coordinate, coordinates[c.index]):
                refitted = float(term.stiffness)
                d.parameters = {"value": refitted, "stiffness": refitted, "springref": float(term.rest)}
    elif c.effect == "joint_armature" and model.armature is not None:
        for coordinate, value in zip(model.armature.coordinates, model.armature.armature):
            if _same(coordinate, coordinates[c.index]):
                refitted = float(value)
    if refitted is not None and np.isfinite(refitted):
        shift = refitted - d.value
        d.ci = (d.ci[0] + shift, d.ci[1] + shift)
        d.value = refitted
        d.parameters["value"] = refitted


def _attribute(
    candidates,
    r_fit,
    f_fit,
    inertial_fit,
    r_held,
    f_held,
    weights,
    smoothing,
    criteria,
    bootstrap,
    max_effects,
    rng,
    round_index,
):
    """Selection, equivalence classes, bootstrap and criteria for one round."""
    # column layout: candidate j owns columns[j]
    columns, signs, start = [], [], 0
    for c in candidates:
        columns.append(list(range(start, start + len(c.columns))))
        signs += list(c.signs)
        start += len(c.columns)
    w = weights[None, None, :, None]
    scale = np.sqrt(np.mean((f_fit * w) ** 2, axis=(0, 1, 2)))
    scale = np.where(scale > 0, scale, 1.0)

    def normals(r, f):
        fw = f * w / scale[None, None, None, :]
        rw = r * weights[None, None, :]
        A = np.einsum("rtmc,rtmd->rcd", fw, fw)
        b = np.einsum("rtmc,rtm->rc", fw, rw)
        c = np.einsum("rtm,rtm->r", rw, rw)
        n = np.full(r.shape[0], r.shape[1] * r.shape[2])
        return A, b, c, n

    A_r, b_r, c_r, n_r = normals(r_fit, f_fit)
    total = _Normal(A_r.sum(0), b_r.sum(0), float(c_r.sum()), int(n_r.sum()))
    A_h, b_h, c_h, n_h = normals(r_held, f_held)
    held = _Normal(A_h.sum(0), b_h.sum(0), float(c_h.sum()), int(n_h.sum()))
    corr = smoothing.correlation
    gain = criteria.min_bic_gain
    select = lambda normal: _forward_select(normal, columns, signs, corr, gain, max_effects)

    def fit_set(normal, groups):
        cols, col_signs = _group_columns(columns, list(groups), signs)
        theta, rss = _fit(normal, cols, col_signs)
        return theta, rss, _bic(rss, normal.n, len(cols), corr)

    def admissible(theta, groups):
        offset = 0
        for g in groups:
            own = theta[offset : offset + len(columns[g])]
            if any(sg > 0 and t <= 0 for sg, t in zip(candidates[g].signs, own)):
                return False
            offset += len(columns[g])
        return True

    chosen = list(select(total).groups)
    # Candidates that explain the data about as well (BIC within `min_bic_gain` when swapped in) cannot
    # be told apart: shoulder damping and linear drag on the elbow keypoint give the very same joint
    # torques, for example. They are reported together, represented by the one earliest in the library.
    classes = []
    for position in range(len(chosen)):
        g = chosen[position]
        _, _, bic_best = fit_set(total, chosen)
        members = [g]
        for h in range(len(candidates)):
            if h in chosen:
                continue
            trial = chosen[:position] + [h] + chosen[position + 1 :]
            theta_h, _, bic_h = fit_set(total, trial)
            if admissible(theta_h, trial) and bic_h - bic_best < gain:
                members.append(h)
        representative = min(members, key=lambda h: (EFFECTS.index(candidates[h].effect), h))
        chosen[position] = representative
        classes.append(set(members))
    theta_all, rss_all, bic_all = fit_set(total, chosen)

    # bootstrap over whole runs: inclusion counts a class when any of its members is selected
    runs = A_r.shape[0]
    inclusion = np.zeros(len(chosen))
    draws = []
    for _ in range(bootstrap):
        counts = np.bincount(rng.integers(0, runs, runs), minlength=runs).astype(float)
        normal = _Normal(
            np.einsum("r,rcd->cd", counts, A_r), counts @ b_r, float(counts @ c_r), int(counts @ n_r)
        )
        picked = set(select(normal).groups)
        inclusion += [bool(picked & members) for members in classes]
        if chosen:
            draws.append(fit_set(normal, chosen)[0])
    inclusion /= max(bootstrap, 1)
    draws = np.array(draws)

    selected = []
    offset = 0
    for position, g in enumerate(chosen):
        c = candidates[g]
        width = len(columns[g])
        theta = theta_all[offset : offset + width] / scale[columns[g]]
        samples = draws[:, offset : offset + width] / scale[columns[g]][None, :] if len(draws) else None
        offset += width
        others = [h for h in chosen if h != g]
        theta_without, rss_without, bic_without = fit_set(total, others)
        cols_with, _ = _group_columns(columns, chosen, signs)
        cols_without, _ = _group_columns(columns, others, signs)
        rss_held_with = _rss(held, cols_with, theta_all)
        rss_held_without = _rss(held, cols_without, theta_without)
        holdout_drop = 1.0 - rss_held_with / rss_held_without if rss_held_without > 0 else 0.0
        sd = float(np.std(samples[:, 0])) if samples is not None and len(samples) > 1 else float("inf")
        t_stat = abs(theta[0]) / sd if sd > 0 else float("inf")
        effect_force = np.einsum("rtmc,c->rtm", f_fit[..., columns[g]], theta)
        share = float(np.sqrt(np.mean(effect_force**2)) / max(np.sqrt(np.mean(inertial_fit**2)), 1e-300))
        main = c.value(theta)
        values = (
            np.array([c.value(v)["value"] for v in samples]) if samples is not None and len(samples) else None
        )
        lo, hi = (
            (float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5)))
            if values is not None
            else (float("nan"), float("nan"))
        )
        alternatives = sorted(candidates[h].label for h in classes[position] if h != g)
        ok = (
            bic_without - bic_all >= gain
            and t_stat >= criteria.min_t
            and inclusion[position] >= criteria.min_inclusion
            and holdout_drop >= criteria.min_holdout_drop
            and share >= criteria.min_share
        )
        selected.append(
            Detection(
                candidate=c,
                value=main["value"],
                ci=(lo, hi),
                parameters=main,
                bic_gain=float(bic_without - bic_all),
                t=float(t_stat),
                inclusion=float(inclusion[position]),
                holdout_drop=float(holdout_drop),
                share=share,
                alternatives=alternatives,
                round=round_index,
                detected=bool(ok),
                theta=theta,
            )
        )
    selected.sort(key=lambda d: -d.bic_gain)
    summary = {
        "round": round_index,
        "candidates": len(candidates),
        "selected": [d.candidate.label for d in selected],
        "detected": [d.candidate.label for d in selected if d.detected],
        "inclusion": {d.candidate.label: d.inclusion for d in selected},
    }
    return {"selected": selected, "summary": summary, "columns": columns}


def _rss(normal: _Normal, columns: list[int], theta: np.ndarray) -> float:
    if not columns:
        return normal.c
    idx = np.asarray(columns)
    return float(normal.c - 2 * theta @ normal.b[idx] + theta @ normal.A[np.ix_(idx, idx)] @ theta)


# -- report -------------------------------------------------------------------------------------


def _markdown(report: dict[str, Any], result: Identification) -> str:
    lines = ["# Missing physics: identification report", ""]
    if report["detected"]:
        lines += [
            "| effect | where | value | 95% interval | BIC gain | t | bootstrap | held-out drop "
            "| alternatives |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for d in report["detected"]:
            ev = d["evidence"]
            name = d["effect"] + (f" ({d['kind']})" if "kind" in d else "")
            lines.append(
                f"| {name} | {d['where']} | {d['value']:.4g} | [{d['ci'][0]:.4g}, {d['ci'][1]:.4g}] | "
                f"{ev['bic_gain']:.1f} | {ev['t']:.1f} | {ev['bootstrap_inclusion']:.2f} | "
                f"{100 * ev['holdout_drop']:.1f}% | {', '.join(d['alternatives']) or '-'} |"
            )
    else:
        lines.append("No missing effect passed the detection criteria.")
    lines += [
        "",
        "| held-out error | before | after | ratio |",
        "| --- | --- | --- | --- |",
    ]
    for key, unit in (("accel_rmse", "m/s^2"), ("rollout_rmse_1s", "m")):
        b, a = report["before"][key], report["after"][key]
        lines.append(f"| {key} ({unit}) | {b:.4g} | {a:.4g} | {b / a if a else float('inf'):.2f}x |")
    if report["rejected"]:
        lines += ["", "Selected but not detected (failed a criterion):", ""]
        for d in report["rejected"]:
            ev = d["evidence"]
            lines.append(
                f"- {d['effect']} at {d['where']}: {d['value']:.3g} (BIC gain {ev['bic_gain']:.1f}, "
                f"t {ev['t']:.1f}, bootstrap {ev['bootstrap_inclusion']:.2f}, "
                f"held-out drop {100 * ev['holdout_drop']:.1f}%, share {100 * ev['share']:.2f}%)"
            )
    s = report["settings"]
    lines += [
        "",
        f"Criteria: {s['criteria']}. Velocities: Savitzky-Golay, window {s['smoothing']['window']}, order "
        f"{s['smoothing']['order']}; equations in weak form, test functions of "
        f"{s['smoothing']['test_width']} samples every {s['smoothing']['test_stride']}. "
        f"{s['runs']} runs ({len(s['held_out_runs'])} held out), "
        f"{s['bootstrap']} bootstrap replicates, seed {s['seed']}; {s['seconds']:.0f} s.",
        "",
        "Plots: `residual_vs_feature.png`, `error_over_time.png`.",
        "",
    ]
    return "\n".join(lines)


def _plots(result: Identification, directory: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = result.curves
    fig, ax = plt.subplots(figsize=(6, 4))
    for key, style in (("before", "C3"), ("after", "C2")):
        err = curves[key]  # (runs, T, keypoints)
        mean = err.mean(axis=(0, 2))
        ax.plot(curves["ts"], 1e3 * mean, style, label=f"{key}: rmse {1e3 * np.sqrt(np.mean(err**2)):.2f} mm")
        ax.fill_between(
            curves["ts"],
            1e3 * np.percentile(err.mean(2), 10, axis=0),
            1e3 * np.percentile(err.mean(2), 90, axis=0),
            color=style,
            alpha=0.15,
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("keypoint position error (mm)")
    ax.set_title("Held-out rollouts: nominal vs. identified model")
    ax.legend()
    fig.tight_layout()
    fig.savefig(directory / "error_over_time.png", dpi=120)
    plt.close(fig)

    n = max(1, len(result.scatter))
    fig, axes = plt.subplots(1, n, figsize=(4.5 * n, 4), squeeze=False)
    for index, (ax, item) in enumerate(zip(axes[0], result.scatter)):
        feature = item["feature"]  # (runs, n, m): the effect's generalised force, weak form
        # the partial residual: what is left for this effect once the other detected effects are removed
        residual = item["residual"] - sum(
            other["feature"]
            for j, other in enumerate(result.scatter)
            if j != index and other["round"] == item["round"]
        )
        component = int(np.argmax(np.mean(feature**2, axis=(0, 1))))
        f = feature[..., component].reshape(-1)
        r = residual[..., component].reshape(-1)
        pick = np.random.default_rng(0).permutation(f.size)[:4000]
        ax.plot(f[pick], r[pick], ".", ms=2, alpha=0.4, color="C0", label="held-out residual")
        line = np.linspace(f.min(), f.max(), 2)
        ax.plot(line, line, "C3", label="identified effect")
        ax.set_xlabel(f"{item['label']} force (joint {component})")
        ax.set_ylabel("partial residual generalised force")
        ax.legend(fontsize=8)
    if not result.scatter:
        axes[0][0].text(0.5, 0.5, "no effect detected", ha="center", va="center")
    fig.tight_layout()
    fig.savefig(directory / "residual_vs_feature.png", dpi=120)
    plt.close(fig)
