"""The loop: residual, attribution, augment and refit, repeated; errors before and after."""

import dataclasses
import time
import warnings
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._consistency import check_constraints
from .._coordinates import AbstractCoordinate, JointMap
from .._data import Sequences
from .._misc import check_fraction, check_positive
from .._progress import AbstractProgressMeter, NoProgressMeter
from .._system import ConstrainedLagrangian
from .adequacy import assess, joint_noise
from .base import AbstractEffect, Context
from .errors import errors
from .library import EFFECTS, resolve
from .limits import limit_contacts
from .refit import augment, refit
from .regression import Criteria, Problem, attribute, coefficients
from .residual import Features, Residual, evaluate
from .result import Curves, Detection, Identification, Scatter
from .smoothing import Prepared, Smoothing, SmoothingChoice, prepare


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
    if joints is None and len(coordinates) + model.num_constraints != model.size:
        raise ValueError(
            f"without joints, the joint coordinates and the constraints must fix the keypoints: "
            f"{len(coordinates)} joint coordinates + {model.num_constraints} constraints != {model.size} "
            "keypoint coordinates (name one coordinate per degree of freedom, or pass joints)"
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


@eqx.filter_jit
def _level(constraint, joints):
    """The values the model holds its constraints at: `Phi(F(q))` for any `q` (zero, say)."""
    return constraint(joints.keypoints(jnp.zeros(joints.num_joints)))


def _check_kinematics(model, joints, x, noise: float, keypoint_names) -> None:
    """Refuse data that break the nominal model's constraints by more than the noise: nothing can be
    attributed to missing physics when the geometry itself is wrong."""
    level = None if joints is None else np.asarray(_level(model.constraint, joints))
    check_constraints(
        model.constraint, x, noise=noise, level=level, keypoint_names=keypoint_names, what="the nominal model"
    )


def _noise_response(model, joints, data, choice, coordinates, tests, weak_residual, seed) -> np.ndarray:
    """The change of the weak residual when simulated position noise of the estimated level is added to
    the measurement: the noise floor of the equations (same shapes, so no new compilation)."""
    rng = np.random.default_rng([seed, 1])
    x = np.asarray(data.x, dtype=float)
    noisy = prepare(
        x + choice.noise * rng.standard_normal(x.shape),
        np.asarray(data.u),
        choice,
        coordinates,
        joints if isinstance(joints, JointMap) else None,
    )
    perturbed = tests.weak(*evaluate(Residual(model, joints), *noisy.arrays()))
    return perturbed[..., 0] - weak_residual[..., 0]


def _exclude_limits(prepared: Prepared, choice: SmoothingChoice, context: Context, joint_limits, tests):
    """Flag the samples at a joint limit; returns the prepared data and a note for the report."""
    if not joint_limits:
        return prepared, []
    dilation = -(-choice.margin // choice.step)
    excluded, notes = limit_contacts(
        prepared.q,
        context.joint_names,
        joint_limits,
        joint_noise(context, prepared.x[0, 0], choice.noise),
        dilation,
    )
    prepared = dataclasses.replace(prepared, excluded=excluded)
    if notes:
        left_out = float(np.mean(tests.support(excluded)))
        notes = [
            "; ".join(notes)
            + f": the model has no joint limits, so {100 * left_out:.0f}% of the weak equations (those that "
            "touch a contact) are left out and held-out rollouts end at the first contact"
        ]
    return prepared, notes


def identify(
    model: ConstrainedLagrangian,
    data: Sequences,
    *,
    joint_coordinates: Mapping[str, AbstractCoordinate],
    joints: JointMap | None = None,
    joint_limits: Mapping[str, tuple[float, float]] | None = None,
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
    refit_potential: bool = True,
    seed: int = 0,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> Identification:
    """Find the effects that a model of a constrained mechanism is missing, add them, and refit.

    0. **Data.** The smoothing and weak-form settings are chosen from the data, in physical time
       (`Smoothing`: the position noise and the motion's time scale are estimated; fast data are
       decimated after smoothing; given `joints`, the smoothing is done on its joint coordinates and
       mapped to the keypoints, which holds fast turns). The measured keypoints must keep the model's
       constraints to within the noise (`cldyn.check_constraints`), else `cldyn.ConstraintViolation`
       is raised: a wrong link length or origin is not missing physics. Samples at a joint limit
       (`joint_limits`) are left out. Whether the data can support a conclusion is judged
       (`Adequacy`: too short, too noisy, motion not resolved, a joint that never moves, a control
       that never varies).
    1. **Residual.** The joint-space residual
       $r = G^T (M(x) \\ddot x - f(x, \\dot x, u))$ with $G = dx/dq$ is what the model misses along
       the constraint manifold (the unknown multipliers drop out), taken in the weak form.
    2. **Attribution.** Every candidate of the effect library is a force linear in its parameters;
       a forward selection by the Bayesian information criterion with sign constraints picks a sparse
       set; a bootstrap over whole runs gives intervals, t-statistics and inclusion probabilities; the
       held-out runs check that each effect improves prediction. An effect is detected only when all
       `Criteria` hold. Candidates that explain the data about as well are reported as alternatives.
    3. **Augment and refit.** Detected effects become cldyn terms (each effect adds its own); the
       potential, the dissipative terms and the armature are refitted by Levenberg-Marquardt. A
       detection stands only if the refitted model's held-out rollout error is lower with it than
       without it (else it is rejected, with a warning); the loop repeats until nothing passes.
    4. **Report.** Errors before and after on held-out runs; the settings chosen, the adequacy of
       the data and the wall time.

    Runs in the precision of the data and the model: float64 (JAX's 64-bit mode) is what the
    tests and the figures use; in float32 the result carries a warning.

    **Arguments:**

    - `model`: the nominal `ConstrainedLagrangian` (analytic, from `from_mjcf`, or learned).
    - `data`: the measured runs, a `cldyn.Sequences`: positions `x` `(runs, T, k)` (possibly noisy),
      controls `u` `(runs, T, l)` as applied, each from its sample to the next, and `dt`.
    - `joint_coordinates`: name -> joint coordinate `q(x)`, for the joint effects (for a MuJoCo
      model: `dict(zip(bridge.joint_names, bridge.joint_coordinates))`).
    - `joints`: the `JointMap` whose Jacobian is the basis `G`, whose keypoints give the levels of the
      constraints the data are checked against, and in whose joint coordinates the positions are
      smoothed (`x = F(q)`, `xd = DF(q) qd`, angles unwrapped); without it, `G = dx/dq` as the joint
      coordinates and the constraints determine it (one joint coordinate per degree of freedom), the
      keypoints are smoothed, and the constraints need only stay constant.
    - `joint_limits`: joint name -> `(low, high)` in the joint coordinate's units, for joints with
      limits the model does not express (`from_mjcf` gives them as `bridge.joint_limits`).
    - `actuator_names`, `keypoint_names`: names for reports; by default `data.info`'s, if it has them.
    - `effects`: the effects to consider, as `AbstractEffect`s or by name (`cldyn.EFFECTS` by
      default). Their order is the order of preference between candidates the data cannot tell apart.
    - `smoothing`, `criteria`: see `Smoothing` and `Criteria`.
    - `holdout`: fraction of runs held out for checks and for the before/after errors.
    - `bootstrap`: bootstrap replicates.
    - `max_rounds`: rounds of detect-augment-refit.
    - `max_effects`: the most effects selected in one round.
    - `horizon`: rollout length (seconds) for `rollout_rmse_1s`.
    - `refit_potential`: refit the potential with the detected effects (step 3); `False` holds it as
      the nominal model has it, for a potential learnt from far more data than `data` (a neural
      potential refitted on a few dozen runs fits them at the expense of other motions).
    - `seed`: for the split, the bootstrap and the simulated noise of the adequacy check.
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

    x = np.asarray(data.x, dtype=float)
    choice = smoothing.choose(x, data.dt)
    _check_kinematics(model, joints, x, choice.noise, context.keypoint_names)
    prepared = prepare(x, np.asarray(data.u), choice, coordinates, joints)
    tests = choice.test_functions(prepared.x.shape[1])
    if tests.count == 0:
        raise ValueError(
            f"runs of {data.num_samples} samples ({(data.num_samples - 1) * data.dt:.3g} s) are too short "
            f"for the smoothing window ({choice.window * data.dt:.3g} s) and a test function "
            f"({choice.test_width * choice.interval:.3g} s)"
        )
    prepared, notes = _exclude_limits(prepared, choice, context, joint_limits, tests)
    problems += notes
    kept = ~tests.support(prepared.excluded)
    runs = data.num_runs
    rng = np.random.default_rng(seed)
    order = rng.permutation(runs)
    n_hold = max(1, int(round(holdout * runs)))
    held, fit_runs = np.sort(order[:n_hold]), np.sort(order[n_hold:])
    fit_data, held_data = prepared.take(fit_runs), prepared.take(held)
    all_candidates = tuple(c for effect in effects for c in effect.candidates(context))
    offsets = np.cumsum([0] + [len(c.columns) for c in all_candidates])

    meter = progress_meter.start(max_rounds + 2, desc="identify", unit="stage")
    try:
        arrays = prepared.arrays()
        frame = joints if joints is not None else coordinates  # what `basis` makes G of
        residual = tests.weak(*evaluate(Residual(model, frame), *arrays))
        noise_response = _noise_response(model, frame, data, choice, coordinates, tests, residual, seed)
        adequacy, examinable = assess(
            context=context,
            candidates=all_candidates,
            choice=choice,
            q=prepared.q,
            x0=prepared.x[0, 0],
            u=np.asarray(data.u),
            kept=kept[fit_runs],
            used=~prepared.excluded,
            inertial=residual[fit_runs, ..., 1],
            noise_response=noise_response[fit_runs],
            criteria=criteria,
        )
        before, ts, error_before = errors(model, held_data, horizon, tests, kept[held], choice.substeps)
        before_excluded = prepared.excluded
        problems += _unconverged("nominal", before)
        meter = progress_meter.update(meter, 1, {"rollout_rmse_1s": before.rollout_rmse_1s})
        # the candidates' features do not change from round to round: evaluate them once, on every run
        features = tests.weak(*evaluate(Features(context, frame, all_candidates), *arrays))
        current, current_errors, error_after = model, before, error_before
        detected: list[Detection] = []
        rejected: list[Detection] = []
        rounds, scatter = [], []
        used: set[str] = set()
        weights = None
        for round_index in range(1, max_rounds + 1):
            active = [j for j in examinable if all_candidates[j].label not in used]
            if not active:
                break
            columns = [col for j in active for col in range(offsets[j], offsets[j + 1])]
            if round_index > 1:
                residual = tests.weak(*evaluate(Residual(current, frame), *arrays))
            r_fit = residual[fit_runs, ..., 0]
            if weights is None:
                spread = (
                    r_fit[kept[fit_runs]].std(axis=0) if kept[fit_runs].any() else np.ones(r_fit.shape[-1])
                )
                weights = 1.0 / np.maximum(spread, 1e-12)
            problem = Problem(
                candidates=tuple(all_candidates[j] for j in active),
                r_fit=r_fit,
                f_fit=features[fit_runs][..., columns],
                inertial_fit=residual[fit_runs, ..., 1],
                r_held=residual[held, ..., 0],
                f_held=features[held][..., columns],
                weights=weights,
                kept_fit=kept[fit_runs],
                kept_held=kept[held],
            )
            result = attribute(
                problem,
                correlation=choice.correlation,
                criteria=criteria,
                bootstrap=bootstrap,
                max_effects=max_effects,
                rng=rng,
                round_index=round_index,
            )
            rounds.append(result.round)
            if result.inadmissible:
                problems.append(
                    f"round {round_index}: the residual asks for "
                    + ", ".join(f.describe() for f in result.inadmissible[:3])
                    + (f" and {len(result.inadmissible) - 3} more" if len(result.inadmissible) > 3 else "")
                    + ": a sign no physical effect has; the nominal model overstates what "
                    + ("it stands" if len(result.inadmissible) == 1 else "they stand")
                    + " for (too much mass or inertia for a negative armature or point mass, energy lost "
                    "that the system keeps for a negative damping)"
                )
            new = [d for d in result.selected if d.detected]
            rejected += [d for d in result.selected if not d.detected]
            info = {"round": round_index, "detected": ", ".join(d.candidate.label for d in new) or "nothing"}
            meter = progress_meter.update(meter, 1 + round_index, info)
            if not new:
                break
            if len(new) < len(result.selected):
                # the coefficients of the detected effects without the selected candidates that failed
                new = _refitted_alone(problem, new)
            outside = _unrepresentable(new, prepared.q, -(-choice.margin // choice.step))
            if outside is not None and (outside & ~prepared.excluded).any():
                problems.append(_unrepresentable_note(new, outside, tests))
                prepared = dataclasses.replace(prepared, excluded=prepared.excluded | outside)
                kept = ~tests.support(prepared.excluded)
                fit_data, held_data = prepared.take(fit_runs), prepared.take(held)
                current_errors, _, error_after = errors(
                    current, held_data, horizon, tests, kept[held], choice.substeps
                )

            def trial_of(detections):
                """The model with `detections` added and refitted, and its held-out errors."""
                augmented = augment(current, detections, context)
                augmented, solved = refit(
                    augmented, fit_data, frame, weights, tests,
                    kept=kept[fit_runs], potential=refit_potential,
                )
                found, _, curve = errors(augmented, held_data, horizon, tests, kept[held], choice.substeps)
                return augmented, solved, found, curve

            trial, solved, trial_errors, trial_curve = trial_of(new)
            # each detection must lower the held-out rollout error: against the others of its round alone
            worse = []
            for d in new if len(new) > 1 else ():
                others = [o for o in new if o is not d]
                # the others' coefficients as the regression gives them without this one
                without = trial_of(_refitted_alone(problem, others))[2]
                if not trial_errors.rollout_rmse_1s < without.rollout_rmse_1s:
                    worse.append(d)
                    problems.append(
                        f"round {round_index}: {d.candidate.label} does not lower the held-out rollout error "
                        f"({without.rollout_rmse_1s:.4g} m without it, {trial_errors.rollout_rmse_1s:.4g} m "
                        "with it): not reported as found"
                    )
            if worse:
                rejected += [
                    dataclasses.replace(d, detected=False, failed=d.failed + ("rollout",)) for d in worse
                ]
                new = [d for d in new if all(d is not w for w in worse)]
                if not new:
                    break
                trial, solved, trial_errors, trial_curve = trial_of(new)
            if not trial_errors.rollout_rmse_1s < current_errors.rollout_rmse_1s:
                labels = ", ".join(d.candidate.label for d in new)
                problems.append(
                    f"round {round_index}: with {labels} the held-out rollout error does not drop "
                    f"({current_errors.rollout_rmse_1s:.4g} -> {trial_errors.rollout_rmse_1s:.4g} m): not "
                    "reported as found (an effect the model cannot express, such as a contact, may be at "
                    "work)"
                )
                rejected += [
                    dataclasses.replace(d, detected=False, failed=d.failed + ("rollout",)) for d in new
                ]
                break
            if solved != optx.RESULTS.successful:
                problems.append(f"the refit of round {round_index} stopped early: {optx.RESULTS[solved]}")
            problems += _unconverged("identified", trial_errors)
            for d in new:
                own = list(result.groups.columns[problem.candidates.index(d.candidate)])
                feature = problem.f_held[..., own] @ np.asarray(d.theta)
                scatter.append(Scatter(d.candidate.label, feature, problem.r_held, round_index))
            used |= {d.candidate.label for d in new}
            current, current_errors, error_after = trial, trial_errors, trial_curve
            detected += [d.refitted(d.candidate.effect.refitted(current, d.candidate, context)) for d in new]
        if (prepared.excluded != before_excluded).any():
            # the errors before and after on the same samples
            before, ts, error_before = errors(model, held_data, horizon, tests, kept[held], choice.substeps)
            if current is model:
                current_errors, error_after = before, error_before
        meter = progress_meter.update(
            meter, max_rounds + 2, {"rollout_rmse_1s": current_errors.rollout_rmse_1s}
        )
    finally:
        progress_meter.close(meter)

    settings = {
        "runs": runs,
        "fit_runs": fit_runs.tolist(),
        "held_out_runs": held.tolist(),
        "dt": float(data.dt),
        "samples": int(data.num_samples),
        "smoothing": choice.to_dict(),
        "excluded_equations": float(1.0 - np.mean(kept)),
        "criteria": criteria.to_dict(),
        "bootstrap": bootstrap,
        "refit_potential": refit_potential,
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
        after=current_errors,
        model=current,
        nominal=model,
        settings=settings,
        rounds=tuple(rounds),
        warnings=tuple(problems),
        adequacy=adequacy,
        curves=Curves(ts, error_before, error_after),
        scatter=tuple(scatter),
    )


def _refitted_alone(problem: Problem, detections: list[Detection]) -> list[Detection]:
    """The detections with the coefficients the regression gives them on their own (their bootstrap
    intervals move with their values)."""
    thetas = coefficients(problem, [problem.candidates.index(d.candidate) for d in detections])
    out = []
    for d, theta in zip(detections, thetas):
        moved = d.refitted(d.candidate.parameters(theta))
        out.append(dataclasses.replace(moved, theta=np.asarray(theta)))
    return out


def _unrepresentable(detections, q: np.ndarray, dilation: int) -> np.ndarray | None:
    """The kept samples at which the terms of `detections` cannot follow their effects, widened by
    `dilation` samples on each side; `None` where they follow them everywhere."""
    masks = [
        m
        for d in detections
        if (m := d.candidate.effect.unrepresentable(d.candidate, d.parameters, q)) is not None
    ]
    if not masks:
        return None
    outside = np.any(masks, axis=0)
    widened = outside.copy()
    for shift in range(1, dilation + 1):
        widened[:, shift:] |= outside[:, :-shift]
        widened[:, :-shift] |= outside[:, shift:]
    return widened


def _unrepresentable_note(detections, outside: np.ndarray, tests) -> str:
    labels = ", ".join(d.candidate.label for d in detections)
    runs = int(outside.any(axis=1).sum())
    share = float(np.mean(tests.support(outside)))
    return (
        f"{labels}: in {runs} of {outside.shape[0]} runs the data go where the model's term cannot follow "
        f"(a hinge spring wound more than half a turn from its rest: keypoints do not count turns); "
        f"{100 * share:.0f}% of the weak equations are left out of the refit, and rollouts end there"
    )


def _unconverged(which: str, errors) -> list[str]:
    out = []
    if errors.unconverged:
        out.append(
            f"the initial-state fit of {errors.unconverged} held-out rollout(s) of the {which} model did not "
            "converge"
        )
    if errors.diverged:
        out.append(f"{errors.diverged} held-out rollout(s) of the {which} model diverged (infinite error)")
    return out
