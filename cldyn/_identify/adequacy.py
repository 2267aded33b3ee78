"""Can the data support a conclusion? Too short, too noisy or too coarsely sampled data make "nothing
detected" meaningless; a joint that never moves or a control that never varies leaves the effects at it
unexaminable. identify reports these instead of silently finding nothing."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .base import Candidate, Context
from .regression import Criteria
from .result import Adequacy
from .smoothing import SmoothingChoice

_JOINT_NOISE_FACTOR = 10.0  # a joint "moves" when its range exceeds this many times its noise
_CONTROL_RTOL = 1e-9


@eqx.filter_jit
def _gradient_norms(coordinates, x):
    return jnp.stack([jnp.linalg.norm(c.gradient(x)) for c in coordinates]) if coordinates else jnp.zeros(0)


def joint_noise(context: Context, x0: np.ndarray, noise: float) -> list[float]:
    """The noise of each joint coordinate: the position noise times `|grad q|`."""
    norms = np.asarray(_gradient_norms(tuple(context.coordinates), jnp.asarray(x0)))
    return [noise * float(n) for n in norms]


def _still_joints(context: Context, q: np.ndarray, x0: np.ndarray, noise: float, used: np.ndarray) -> dict:
    out = {}
    for j, (name, sigma) in enumerate(zip(context.joint_names, joint_noise(context, x0, noise))):
        values = q[..., j][used]
        spread = float(values.max() - values.min()) if values.size else 0.0
        if spread <= max(_JOINT_NOISE_FACTOR * sigma, 1e-9):
            out[name] = f"joint {name!r} never moves (range {spread:.3g} against noise {sigma:.3g})"
    return out


def _constant_controls(context: Context, u: np.ndarray) -> dict:
    out = {}
    flat = u.reshape(-1, u.shape[-1])
    for a, name in enumerate(context.actuator_names):
        column = flat[:, a]
        size = float(np.max(np.abs(column))) if column.size else 0.0
        if size == 0.0:
            out[name] = f"actuator {name!r} is never driven (its control is zero throughout)"
        elif float(np.std(column)) <= _CONTROL_RTOL * size:
            out[name] = (
                f"actuator {name!r} holds one control ({column[0]:.3g}) throughout: its gain acts as a "
                "constant force"
            )
    return out


def assess(
    *,
    context: Context,
    candidates: tuple[Candidate, ...],
    choice: SmoothingChoice,
    q: np.ndarray,
    x0: np.ndarray,
    u: np.ndarray,
    kept: np.ndarray,
    used: np.ndarray,
    inertial: np.ndarray,
    noise_response: np.ndarray,
    criteria: Criteria,
) -> tuple[Adequacy, tuple[int, ...]]:
    """Judge what the data can support.

    **Arguments:** the `context` and `candidates`; the `choice` of smoothing; the joint coordinates
    `q` `(runs, T', m)` at the kept samples, one position `x0`, and the controls `u` `(runs, T, l)`;
    `kept` `(runs, n)`, the weak equations of the fit runs that count; `used` `(runs, T')`, the samples
    not excluded; `inertial` `(runs, n, m)`, the fit runs' weak inertial forces; `noise_response`, the
    change of their weak residual under simulated noise; the `criteria`.

    **Returns:** `(Adequacy, indices of the candidates that can be examined)`.
    """
    problems = []
    rows = float(kept.sum())
    equations = rows / choice.correlation
    if equations < criteria.min_equations:
        problems.append(
            f"too short: {equations:.0f} independent equations per joint in the fit runs, fewer than "
            f"{criteria.min_equations:g} (longer or more runs are needed)"
        )
    per_timescale = choice.timescale / choice.dt
    if per_timescale < criteria.min_samples_per_timescale:
        problems.append(
            f"sampled too coarsely: {per_timescale:.2g} samples per time scale of the motion "
            f"({choice.timescale:.3g} s at {choice.dt:.3g} s), fewer than "
            f"{criteria.min_samples_per_timescale:g}"
        )
    weight = kept[..., None]
    inertial_rms = math.sqrt(float(np.sum((inertial * weight) ** 2)) / max(rows * inertial.shape[-1], 1.0))
    noise_rms = math.sqrt(float(np.sum((noise_response * weight) ** 2)) / max(rows * inertial.shape[-1], 1.0))
    n_eff = max(equations * inertial.shape[-1], 2.0)
    if inertial_rms > 0:
        growth = math.expm1(min((criteria.min_bic_gain + math.log(n_eff)) / n_eff, 700.0))
        share = noise_rms / inertial_rms * math.sqrt(growth)
    else:
        share = float("inf")
    if share > criteria.max_detectable_share:
        problems.append(
            f"too noisy: only effects above {100 * share:.2g}% of the inertial forces could be detected "
            f"(position noise {choice.noise:.3g} m; the limit is {100 * criteria.max_detectable_share:g}%)"
        )
    reasons = {
        "joint": _still_joints(context, q, x0, choice.noise, used),
        "actuator": _constant_controls(context, u),
    }
    unexamined, examinable = [], []
    for index, candidate in enumerate(candidates):
        why = reasons.get(candidate.acts_on, {}).get(candidate.where)
        if why is not None:
            unexamined.append((candidate.label, why))
        else:
            examinable.append(index)
    adequacy = Adequacy(tuple(problems), tuple(unexamined), float(share), float(equations))
    return adequacy, tuple(examinable)
