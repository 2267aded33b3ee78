"""The loop: residual, attribution, augment and refit, repeated; errors before and after."""

import dataclasses
import time
import warnings
from collections.abc import Mapping, Sequence

import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._coordinates import AbstractCoordinate, JointMap
from .._data import Sequences
from .._misc import check_fraction, check_positive
from .._progress import AbstractProgressMeter, NoProgressMeter
from .._system import ConstrainedLagrangian
from .base import AbstractEffect, Context
from .errors import errors
from .library import EFFECTS, resolve
from .refit import augment, refit
from .regression import Criteria, Problem, attribute
from .residual import Features, Residual, evaluate
from .result import Curves, Detection, Identification, Scatter
from .smoothing import Smoothing, prepare


def _names(given, info, key: str, count: int, default: str) -> tuple[str, ...]:
    names = given if given is not None else info.get(key)
    if names is None or len(names) != count:
        if given is not None:
            raise ValueError(f"{key} has {len(given)} names for {count} {default}s")
        names = [f"{default}{i}" for i in range(count)]
    return tuple(str(n) for n in names)


def _check(model, data, coordinates, joints, runs_needed: int = 4) -> None:
    if not isinstance(model, ConstrainedLagrangian) or model.num_constraints == 0:
        raise TypeError("identify needs a ConstrainedLagrangian with constraints")
    if not isinstance(data, Sequences):
        raise TypeError(f"identify takes its data as a cldyn.Sequences, got {type(data).__name__}")
    if joints is not None and joints.num_joints != len(coordinates):
        raise ValueError(
            f"joints has {joints.num_joints} joint coordinates but joint_coordinates has {len(coordinates)}"
        )
    if data.size != model.size:
        raise ValueError(f"x must have shape (runs, T, {model.size}), got {tuple(data.x.shape)}")
    if data.num_inputs != model.num_inputs:
        raise ValueError(
            f"u must have {model.num_inputs} controls per sample, got shape {tuple(data.u.shape)}"
        )
    if data.num_runs < runs_needed:
        raise ValueError(
            f"identify needs at least {runs_needed} runs (for held-out checks and bootstrap), got "
            f"{data.num_runs}"
        )


def identify(
    model: ConstrainedLagrangian,
    data: Sequences,
    *,
    joint_coordinates: Mapping[str, AbstractCoordinate],
    joints: JointMap | None = None,
    actuator_names: Sequence[str] | None = None,
    keypoint_names: Sequence[str] | None = None,
    effects: Sequence[AbstractEffect | str] = EFFECTS,
    smoothing: Smoothing = Smoothing(),
    criteria: Criteria = Criteria(),
    holdout: float = 0.25,
    bootstrap: int = 100,
    max_rounds: int = 3,
    max_effects: int = 4,
    horizon: float = 1.0,
    seed: int = 0,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> Identification:
    """Find the effects that a model of a constrained mechanism is missing, add them, and refit.

    1. **Residual.** Positions are smoothed and differentiated (`Smoothing`); the joint-space residual
       $r = G^T (M(x) \\ddot x - f(x, \\dot x, u))$ with $G = dx/dq$ is what the model misses along
       the constraint manifold (the unknown multipliers drop out), taken in the weak form.
    2. **Attribution.** Every candidate of the effect library is a force linear in its parameters;
       a forward selection by the Bayesian information criterion with sign constraints picks a sparse
       set; a bootstrap over whole runs gives intervals, t-statistics and inclusion probabilities; the
       held-out runs check that each effect improves prediction. An effect is detected only when all
       `Criteria` hold. Candidates that explain the data about as well are reported as alternatives.
    3. **Augment and refit.** Detected effects become cldyn terms (each effect adds its own); the
       potential, the dissipative terms and the armature are refitted by Levenberg-Marquardt; the loop
       repeats until nothing passes.
    4. **Report.** Errors before and after on held-out runs.

    Runs in the precision of the data and the model: float64 (JAX's 64-bit mode) is what the
    tests and the figures use; in float32 the result carries a warning.

    **Arguments:**

    - `model`: the nominal `ConstrainedLagrangian` (analytic, from `from_mjcf`, or learned).
    - `data`: the measured runs, a `cldyn.Sequences`: positions `x` `(runs, T, k)` (possibly noisy),
      controls `u` `(runs, T, l)` applied from each sample to the next, and `dt`.
    - `joint_coordinates`: name -> joint coordinate `q(x)`, for the joint effects (for a MuJoCo
      model: `dict(zip(bridge.joint_names, bridge.joint_coordinates))`).
    - `joints`: the `JointMap` whose Jacobian is the basis `G`; without it, an orthonormal basis of
      the tangent space.
    - `actuator_names`, `keypoint_names`: names for reports; by default `data.info`'s, if it has them.
    - `effects`: the effects to consider, as `AbstractEffect`s or by name (`cldyn.EFFECTS` by
      default). Their order is the order of preference between candidates the data cannot tell apart.
    - `smoothing`, `criteria`: see `Smoothing` and `Criteria`.
    - `holdout`: fraction of runs held out for checks and for the before/after errors.
    - `bootstrap`: bootstrap replicates.
    - `max_rounds`: rounds of detect-augment-refit.
    - `max_effects`: the most effects selected in one round.
    - `horizon`: rollout length (seconds) for `rollout_rmse_1s`.
    - `seed`: for the split and the bootstrap.
    - `progress_meter`: how to report progress (`cldyn.TextProgressMeter()`, ...); silent by default.

    **Returns:** an `Identification`; `.save(dir)` writes the report and the plots.

    !!! example

        ```python
        data = cldyn.Sequences(x, u, dt=0.01)
        result = cldyn.identify(model, data, joint_coordinates={"hinge": cldyn.HingeAngle(child=(None, 0))},
                                joints=joint_map)
        print(result.summary())
        ```
    """
    started = time.perf_counter()
    names = tuple(joint_coordinates)
    coordinates = tuple(joint_coordinates[n] for n in names)
    _check(model, data, coordinates, joints)
    check_fraction("holdout", holdout)
    for name, number in (("bootstrap", bootstrap), ("max_rounds", max_rounds), ("max_effects", max_effects)):
        check_positive(name, number, integer=True)
    check_positive("horizon", horizon)
    effects = resolve(effects)
    context = Context(
        model,
        coordinates,
        names,
        _names(actuator_names, data.info, "actuator_names", model.num_inputs, "u"),
        _names(keypoint_names, data.info, "keypoint_names", model.size // 2, "keypoint"),
    )
    problems = []
    if jnp.zeros((), jnp.float64).dtype != jnp.float64:
        problems.append("runs in float32: JAX's 64-bit mode is off, figures may be inaccurate")
        warnings.warn(f"identify {problems[-1]}", stacklevel=2)

    prepared = prepare(np.asarray(data.x), np.asarray(data.u), data.dt, smoothing, coordinates)
    runs = data.num_runs
    rng = np.random.default_rng(seed)
    order = rng.permutation(runs)
    n_hold = max(1, int(round(holdout * runs)))
    held, fit_runs = np.sort(order[:n_hold]), np.sort(order[n_hold:])
    fit_data, held_data = prepared.take(fit_runs), prepared.take(held)
    tests = smoothing.test_functions(prepared.x.shape[1], data.dt)
    if tests.count == 0:
        raise ValueError(
            f"runs of {data.num_samples} samples are too short for the smoothing window {smoothing.window} "
            f"and test functions of {smoothing.test_width} samples"
        )
    all_candidates = tuple(c for effect in effects for c in effect.candidates(context))
    offsets = np.cumsum([0] + [len(c.columns) for c in all_candidates])

    meter = progress_meter.start(max_rounds + 2, desc="identify", unit="stage")
    try:
        before, ts, error_before = errors(model, held_data, horizon, tests)
        problems += _unconverged("nominal", before.unconverged)
        meter = progress_meter.update(meter, 1, {"rollout_rmse_1s": before.rollout_rmse_1s})
        arrays = prepared.arrays()
        # the candidates' features do not change from round to round: evaluate them once, on every run
        features = tests.weak(*evaluate(Features(context, joints, all_candidates), *arrays))
        current = model
        detected: list[Detection] = []
        rejected: list[Detection] = []
        rounds, scatter = [], []
        used: set[str] = set()
        weights = None
        for round_index in range(1, max_rounds + 1):
            active = [j for j, c in enumerate(all_candidates) if c.label not in used]
            if not active:
                break
            columns = [col for j in active for col in range(offsets[j], offsets[j + 1])]
            residual = tests.weak(*evaluate(Residual(current, joints), *arrays))
            r_fit = residual[fit_runs, ..., 0]
            if weights is None:
                weights = 1.0 / np.maximum(r_fit.reshape(-1, r_fit.shape[-1]).std(axis=0), 1e-12)
            problem = Problem(
                candidates=tuple(all_candidates[j] for j in active),
                r_fit=r_fit,
                f_fit=features[fit_runs][..., columns],
                inertial_fit=residual[fit_runs, ..., 1],
                r_held=residual[held, ..., 0],
                f_held=features[held][..., columns],
                weights=weights,
            )
            result = attribute(
                problem,
                correlation=smoothing.correlation,
                criteria=criteria,
                bootstrap=bootstrap,
                max_effects=max_effects,
                rng=rng,
                round_index=round_index,
            )
            rounds.append(result.round)
            new = [d for d in result.selected if d.detected]
            rejected += [d for d in result.selected if not d.detected]
            info = {"round": round_index, "detected": ", ".join(d.candidate.label for d in new) or "nothing"}
            meter = progress_meter.update(meter, 1 + round_index, info)
            if not new:
                break
            for d in new:
                own = list(result.groups.columns[problem.candidates.index(d.candidate)])
                feature = problem.f_held[..., own] @ np.asarray(d.theta)
                scatter.append(Scatter(d.candidate.label, feature, problem.r_held, round_index))
            used |= {d.candidate.label for d in new}
            current = augment(current, new, context)
            current, solved = refit(current, fit_data, joints, weights, tests)
            if solved != optx.RESULTS.successful:
                problems.append(f"the refit of round {round_index} stopped early: {optx.RESULTS[solved]}")
            detected += [d.refitted(d.candidate.effect.refitted(current, d.candidate, context)) for d in new]

        after, _, error_after = errors(current, held_data, horizon, tests)
        problems += _unconverged("identified", after.unconverged)
        meter = progress_meter.update(meter, max_rounds + 2, {"rollout_rmse_1s": after.rollout_rmse_1s})
    finally:
        progress_meter.close(meter)

    settings = {
        "runs": runs,
        "fit_runs": fit_runs.tolist(),
        "held_out_runs": held.tolist(),
        "dt": float(data.dt),
        "smoothing": {
            "velocities": "savitzky-golay",
            "window": smoothing.window,
            "order": smoothing.order,
            "equations": "weak form, test functions (1 - s^2)^4",
            "test_width": smoothing.test_width,
            "test_stride": smoothing.test_stride,
        },
        "criteria": criteria.to_dict(),
        "bootstrap": bootstrap,
        "effects": [e.name for e in effects],
        "effect_options": {
            e.name: {f.name: getattr(e, f.name) for f in dataclasses.fields(e)}
            for e in effects
            if dataclasses.fields(e)
        },
        "seed": seed,
        "seconds": time.perf_counter() - started,
    }
    return Identification(
        detected=tuple(detected),
        rejected=tuple(rejected),
        before=before,
        after=after,
        model=current,
        nominal=model,
        settings=settings,
        rounds=tuple(rounds),
        warnings=tuple(problems),
        curves=Curves(ts, error_before, error_after),
        scatter=tuple(scatter),
    )


def _unconverged(which: str, count: int) -> list[str]:
    if not count:
        return []
    return [f"the initial-state fit of {count} held-out rollout(s) of the {which} model did not converge"]
