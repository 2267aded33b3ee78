"""cldyn.identify: finding the physics a model is missing, without MuJoCo.

The pieces are checked against independent facts (derivatives of known functions, constrained least
squares by brute force, the weak form on exact trajectories); the loop against data integrated in
generalised coordinates by the references of tests/helpers.py, which carry the missing effect as a
joint-space force written independently of cldyn's terms. The MuJoCo acceptance matrix is in
test_identify_mujoco.py.
"""

import dataclasses
import functools
import importlib.util
import itertools
import json
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import reference_systems, simulate_reference

import cldyn
from cldyn._identify.regression import Groups, Normal, fit, inadmissible
from cldyn._identify.smoothing import periodic_joints, prepare, smooth_in_joints

DAMPING_RTOL = 0.05  # linear damping beside the quadratic one, on exact data
QUADRATIC_RTOL = 0.15  # the acceptance figure for the new effect
MIN_ROLLOUT_DROP = 5.0
DAMPING_RATES_RTOL = 0.15  # the acceptance figure, at either rate
RATE_AGREEMENT = 0.05  # the same data at 1 kHz and thinned to 100 Hz
WEAK_RESIDUAL_RTOL = 1e-4  # weak residual of the exact model / inertial forces
SMOOTHING_ATOL = (1e-12, 1e-9, 1e-6)  # a degree-4 polynomial: position, velocity, acceleration
SINE_RTOL = 1e-4
BY_PARTS_RTOL = 1e-4  # the sums of the quadrature against the integrals (2e-5 here)
NOISE_RTOL = 0.05  # noise estimated from 6 runs of 4 s
DECIMATION_RTOL = 2e-3  # weak integrals from kept samples against every sample
JOINT_SMOOTHING_ATOL = (1e-9, 1e-8, 1e-6)  # joint angles quadratic in time: x, xd, xdd
# the damped acrobot at 20 Hz: 0.9%, 3.4% (one rollout step per sample diverged there and nothing was
# detected; at 25 Hz, 0.2%, 0.7% through the joints against 2.8%, 3.4% through the keypoints)
FAST_TURNS_RTOL = 0.05


# -- pieces -------------------------------------------------------------------------------------


def test_smoothing_differentiates_polynomials_exactly_and_sines_accurately():
    dt = 0.01
    t = np.arange(200) * dt
    choice = cldyn.Smoothing(window=0.09, order=4, decimate=False).choose(np.zeros((1, t.size, 1)), dt)
    assert choice.window == 9 and choice.step == 1
    m = choice.margin
    poly = 1.0 + 2.0 * t - 3.0 * t**2 + 0.5 * t**4
    x, xd, xdd = choice.smooth(poly[None, :, None])
    interior = t[m:-m]
    assert np.allclose(x[0, :, 0], poly[m:-m], atol=SMOOTHING_ATOL[0])
    assert np.allclose(xd[0, :, 0], 2 - 6 * interior + 2 * interior**3, atol=SMOOTHING_ATOL[1])
    assert np.allclose(xdd[0, :, 0], -6 + 6 * interior**2, atol=SMOOTHING_ATOL[2])
    omega = 6.0
    x, xd, _ = choice.smooth(np.sin(omega * t)[None, :, None])
    assert np.max(np.abs(xd[0, :, 0] - omega * np.cos(omega * interior))) < SINE_RTOL * omega


def test_smoothing_in_joint_coordinates_holds_fast_turns_exactly():
    # joint angles quadratic in time, 0.4 rad per sample: a degree-4 polynomial through the keypoints'
    # arcs misses their velocity, through the angles it is exact; the truth is F(q(t)) differentiated
    # in time by JAX
    _, joints, _ = reference_systems()["acrobot"]
    dt = 0.04
    t = np.arange(40) * dt
    a, b, c = jnp.array([0.3, -1.0]), jnp.array([10.0, -7.0]), jnp.array([-4.0, 6.0])
    path = lambda s: joints.keypoints(a + b * s + c * s**2)  # noqa: E731
    x = np.asarray(jax.vmap(path)(jnp.asarray(t)))[None]
    choice = cldyn.Smoothing(window=11 * dt, order=4, decimate=False).choose(np.zeros((1, t.size, 1)), dt)
    assert choice.window == 11 and choice.step == 1
    inner = jnp.asarray(t[choice.margin : -choice.margin])
    truth = (
        jax.vmap(path)(inner),
        jax.vmap(jax.jacfwd(path))(inner),
        jax.vmap(jax.jacfwd(jax.jacfwd(path)))(inner),
    )
    for smoothed, expected, atol in zip(smooth_in_joints(choice, joints, x), truth, JOINT_SMOOTHING_ATOL):
        assert np.allclose(smoothed[0], expected, atol=atol)
    _, keypoint_velocity, _ = choice.smooth(x)
    assert np.max(np.abs(keypoint_velocity[0] - truth[1])) > 0.05  # the premise: the keypoints' arcs


def test_the_angles_of_a_joint_map_are_found_by_a_turn():
    _, acrobot, _ = reference_systems()["acrobot"]
    _, cartpole, _ = reference_systems()["cartpole"]
    assert periodic_joints(acrobot, acrobot.keypoints(jnp.array([0.4, -2.0]))).tolist() == [True, True]
    # the cart's slider is a length, the pole's hinge an angle
    assert periodic_joints(cartpole, cartpole.keypoints(jnp.array([0.3, 1.0]))).tolist() == [False, True]


def test_test_functions_integrate_derivatives_by_parts():
    # int psi f' dt = -int psi' f dt for a smooth f: the identity the weak form rests on
    dt = 0.01
    t = np.arange(300) * dt
    choice = cldyn.Smoothing(window=0.11, test_width=0.31, test_stride=0.05).choose(np.zeros((1, 300, 1)), dt)
    assert (choice.test_width, choice.test_stride, choice.step) == (31, 5, 1)
    tests = choice.test_functions(t.size)
    f, fd = np.sin(3 * t) + t**2, 3 * np.cos(3 * t) + 2 * t
    assert np.allclose(tests.psi @ np.ones_like(t), 1.0)
    scale = np.max(np.abs(tests.psi @ fd))
    assert np.max(np.abs(tests.psi @ fd + tests.dpsi @ f)) < BY_PARTS_RTOL * scale


def _noisy_motion(dt, sigma, *, seconds=4.0, runs=6, seed=0):
    """Smooth runs `(runs, T, 2)`: sums of sines of angular frequencies 2 to 5 rad/s, with white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(seconds / dt)) + 1) * dt
    frequencies = rng.uniform(2.0, 5.0, size=(runs, 1, 2, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(runs, 1, 2, 3))
    x = 0.5 * np.sin(frequencies * t[None, :, None, None] + phases).sum(axis=-1)
    return x + sigma * np.random.default_rng(seed + 1).standard_normal(x.shape)


@pytest.mark.parametrize("dt", [0.0005, 0.01])
def test_noise_is_estimated_from_the_data(dt):
    for sigma in (0.001, 0.003):
        estimate = cldyn.estimate_noise(_noisy_motion(dt, sigma))
        assert abs(estimate - sigma) < NOISE_RTOL * sigma, (dt, sigma, estimate)
    assert cldyn.estimate_noise(_noisy_motion(dt, 0.0)) < 1e-2 * 0.001


def test_smoothing_is_chosen_in_physical_time():
    # the same motion and noise sampled at 2 kHz and at 100 Hz: test functions of the same length in
    # seconds (twice the time scale, 1 / RMS frequency of the velocity), windows of similar length
    # (the rate only changes how many samples average the noise), fast data decimated to a few
    # samples per window
    fast = cldyn.Smoothing().choose(_noisy_motion(0.0005, 0.001), 0.0005)
    slow = cldyn.Smoothing().choose(_noisy_motion(0.01, 0.001), 0.01)
    for choice in (fast, slow):
        assert abs(choice.noise - 0.001) < NOISE_RTOL * 0.001
        # the motion's time scale, sqrt(<v^2> / <a^2>) of sines of 2 to 5 rad/s: between 1/5 and 1/2 s
        assert 0.2 < choice.timescale < 0.5
    assert abs(fast.timescale - slow.timescale) < 0.05 * slow.timescale
    fast_test, slow_test = (c.test_width * c.interval for c in (fast, slow))
    assert abs(fast_test - slow_test) < 0.1 * slow_test
    assert 0.5 < fast.window * fast.dt / (slow.window * slow.dt) < 2.0
    assert fast.step > 10 and fast.interval <= fast.window * fast.dt / 10
    # given settings are kept, in seconds
    given = cldyn.Smoothing(window=0.05, test_width=0.4).choose(_noisy_motion(0.0005, 0.001), 0.0005)
    assert given.window == 101 and abs(given.test_width * given.interval - 0.4) <= 1.01 * given.interval
    assert given.chosen["window"] == given.chosen["test_width"] == "given"


def test_decimation_keeps_the_weak_integrals():
    # int psi' x dt over the kept samples against the same test functions integrated over every
    # sample of the same smoothed positions: only the quadrature differs
    dt = 0.0005
    x = _noisy_motion(dt, 0.001, runs=2)
    thinned = cldyn.Smoothing().choose(x, dt)
    assert thinned.step > 10
    kept = prepare(x, np.zeros(x.shape[:2] + (0,)), thinned, ())
    tests = thinned.test_functions(kept.x.shape[1])
    coarse = np.einsum("nt,rtk->rnk", tests.dpsi, kept.x)
    every = dataclasses.replace(thinned, step=1)
    smooth = every.smooth(x)[0]
    # the test functions in time: (1 - s^2)^4 about each centre, half-width (half + 1) kept intervals
    t_kept = np.arange(kept.x.shape[1]) * thinned.interval
    t_all = np.arange(smooth.shape[1]) * dt
    half = (thinned.test_width // 2 + 1) * thinned.interval
    centres = t_kept[thinned.test_width // 2 :: thinned.test_stride][: tests.count]
    s_ = (t_all[None, :] - centres[:, None]) / half
    inside = np.abs(s_) < 1
    psi = np.where(inside, (1 - s_**2) ** 4, 0.0)
    dpsi = np.where(inside, -8 * s_ * (1 - s_**2) ** 3 / half, 0.0)
    fine = np.einsum("nt,rtk->rnk", dpsi / (psi.sum(axis=1, keepdims=True) * dt) * dt, smooth)
    assert np.max(np.abs(coarse - fine)) < DECIMATION_RTOL * np.max(np.abs(fine))


def test_constrained_least_squares_matches_brute_force():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 4))
    b = A @ np.array([0.5, -0.3, 0.2, -0.8]) + 0.01 * rng.normal(size=200)
    normal = Normal(A.T @ A, A.T @ b, float(b @ b), 200)
    signs = [1, 1, 0, 1]
    theta, rss = fit(normal, [0, 1, 2, 3], signs)
    # brute force over every subset of sign-constrained variables pinned at zero
    best = None
    for pinned in itertools.chain.from_iterable(itertools.combinations([0, 1, 3], r) for r in range(4)):
        free = [i for i in range(4) if i not in pinned]
        sol = np.zeros(4)
        sol[free] = np.linalg.lstsq(A[:, free], b, rcond=None)[0]
        if all(sol[i] >= 0 for i in (0, 1, 3)):
            r = np.sum((A @ sol - b) ** 2)
            best = r if best is None else min(best, r)
    assert np.isclose(rss, best, rtol=1e-10)
    assert theta[1] == 0.0 and theta[3] == 0.0 and theta[0] > 0


def test_a_residual_that_asks_for_a_forbidden_sign_is_named_not_detected():
    # columns of a damping, an armature (both non-negative by physics) and an actuator gain (free);
    # the residual holds -0.4 of the armature's column: a model with too much inertia
    from cldyn._identify.base import Candidate
    from cldyn._identify.library import ActuatorGainEffect, JointArmatureEffect, JointDampingEffect

    rng = np.random.default_rng(1)
    F = rng.normal(size=(400, 3))
    r = -0.4 * F[:, 1] + 0.3 * F[:, 2] + 0.05 * rng.normal(size=400)
    normal = Normal(F.T @ F, F.T @ r, float(r @ r), 400)
    candidates = (
        Candidate(JointDampingEffect(), "hinge", 0),
        Candidate(JointArmatureEffect(), "hinge", 0),
        Candidate(ActuatorGainEffect(), "motor", 0, acts_on="actuator"),
    )
    groups = Groups.of(candidates)
    scale = np.ones(3)
    # with the gain selected, the armature's least-squares coefficient is -0.4: named, with its BIC gain
    found = inadmissible(normal, groups, candidates, [2], correlation=1.0, min_gain=10.0, scale=scale)
    assert [f.label for f in found] == ["joint_armature[hinge]"]
    assert found[0].value == pytest.approx(-0.4, abs=0.01)
    _, rss_without = fit(normal, [2], [0])
    _, rss_with = fit(normal, [2, 1], [0, 0])
    expected_gain = 400 * np.log(rss_without / rss_with) - np.log(400)  # BIC, one more parameter
    assert found[0].bic_gain == pytest.approx(expected_gain, rel=1e-9)
    # the same residual with the sign flipped is an admissible armature: nothing named
    positive = 0.8 * F[:, 1] + r
    flipped = Normal(F.T @ F, F.T @ positive, float(positive @ positive), 400)
    assert inadmissible(flipped, groups, candidates, [2], correlation=1.0, min_gain=10.0, scale=scale) == ()


# -- data from independent references ------------------------------------------------------------


def _hinges(n):
    """The chain's joint coordinates: link 0 against straight down, link i against link i - 1."""
    out = [cldyn.HingeAngle(child=(None, 0))]
    out += [
        cldyn.HingeAngle(child=(i - 1, i), parent=(None if i == 1 else i - 2, i - 1)) for i in range(1, n)
    ]
    return out


def _reference_data(name, force=None, *, runs=16, seconds=3.0, dt=0.01, spread=2.5, control=1.0, seed=0):
    """Runs of a reference chain from random rest states, with one random constant control per run,
    integrated in joint space with `force(q, qd)` added; returns `(system, joints, data, names)`."""
    system, joints, reference = reference_systems()[name]
    n = reference.n
    rng = np.random.default_rng(seed)
    samples = int(round(seconds / dt)) + 1
    q0 = rng.uniform(-spread, spread, size=(runs, n))
    u = rng.uniform(-control, control, size=(runs, system.num_inputs))
    us = np.broadcast_to(u[:, None, :], (runs, samples, system.num_inputs))

    @jax.jit
    def run(q0, us):
        return jax.vmap(
            lambda a, b: simulate_reference(reference, a, jnp.zeros(n), b, dt, samples, force=force)
        )(q0, us)[0]

    x = np.asarray(run(jnp.asarray(q0), jnp.asarray(us)))
    names = ["shoulder", "elbow", "wrist"][:n] if n > 1 else ["hinge"]
    return system, joints, cldyn.Sequences(x, np.array(us), dt), dict(zip(names, _hinges(n)))


@functools.cache
def _effect_free_pendulum():
    return _reference_data("pendulum", runs=4)


def test_weak_residual_of_the_true_model_vanishes():
    from cldyn._identify.residual import Residual, evaluate

    system, joints, data, coordinates = _effect_free_pendulum()
    choice = cldyn.Smoothing().choose(data.x, data.dt)
    prepared = prepare(data.x, data.u, choice, tuple(coordinates.values()))
    tests = choice.test_functions(prepared.x.shape[1])
    weak = tests.weak(*evaluate(Residual(system, joints), *prepared.arrays()))
    residual, inertial = weak[..., 0], weak[..., 1]
    assert np.sqrt(np.mean(residual**2)) < WEAK_RESIDUAL_RTOL * np.sqrt(np.mean(inertial**2))


def test_identifys_rollouts_are_cldyns_rollouts():
    """identify's own rollout loop (a scan with RK4's stages looped, for compile time) integrates the
    same scheme as `cldyn.rollout` (diffrax, RK4 with the projection, controls held): the same
    positions to rounding, from states off the constraints' tangent space, with controls and
    damping; and on a run too fast for the step, whose projection fails, both keep that step and leave
    every later position infinite."""
    from cldyn._identify.errors import _step_rollout

    system, joints, _ = reference_systems()["acrobot"]
    m = joints.num_joints
    damping = cldyn.JointDamping(_hinges(m), jnp.linspace(0.2, 0.5, m))
    damped = eqx.tree_at(lambda s: s.dissipation, system, damping, is_leaf=lambda v: v is None)
    rng = np.random.default_rng(5)
    q0, qd0 = rng.uniform(-1.5, 1.5, (4, m)), rng.uniform(-2.0, 2.0, (4, m))
    qd0[3] = (60.0, -80.0)  # rad/s: at 10 ms steps the projection fails after a few steps
    x0, xd0 = jax.vmap(joints.to_keypoints)(jnp.asarray(q0), jnp.asarray(qd0))
    xd0 = xd0 + 0.05 * jnp.asarray(rng.standard_normal(xd0.shape))
    us = jnp.asarray(rng.uniform(-1.0, 1.0, (4, 151, system.num_inputs)))
    expected = jax.vmap(lambda a, b, c: cldyn.rollout(damped, a, b, c, 0.01, throw=False).x)(x0, xd0, us)
    found = jax.jit(jax.vmap(lambda a, b, c: _step_rollout(damped, a, b, c, 0.01)))(x0, xd0, us)
    expected, found = np.asarray(expected), np.asarray(found)
    taken = np.isfinite(expected).all(axis=-1)
    steps = int(taken[3].sum())
    assert taken[:3].all() and 1 < steps < taken.shape[1] and not taken[3, steps:].any()
    np.testing.assert_array_equal(np.isinf(found), np.isinf(expected))
    assert np.max(np.abs(found[taken] - expected[taken])) < 1e-12 * np.max(np.abs(expected[taken]))


@pytest.mark.slow
def test_identify_finds_linear_and_quadratic_joint_damping(tmp_path):
    # the acceptance figure of the new effect: aerodynamic drag -c |qd| qd on the acrobot's elbow,
    # beside viscous damping -b qd on its shoulder, both integrated in joint space by the reference
    # (not by cldyn's JointDamping or JointQuadraticDamping)
    b, c = 0.05, 0.02
    system, joints, data, coordinates = _reference_data(
        "acrobot", lambda q, qd: jnp.array([-b * qd[0], -c * jnp.abs(qd[1]) * qd[1]]), seed=1
    )
    meter = cldyn.TextProgressMeter(interval=0.0)
    result = cldyn.identify(
        system, data, joint_coordinates=coordinates, joints=joints, bootstrap=40, progress_meter=meter
    )
    found = {(d.name, d.where): d for d in result.detected}
    assert set(found) == {("joint_damping", "shoulder"), ("joint_quadratic_damping", "elbow")}, [
        d.to_dict() for d in result.detected
    ]
    quadratic = found[("joint_quadratic_damping", "elbow")]
    print(
        f"quadratic damping at the elbow: {quadratic.value:.6g} (truth {c}); "
        f"linear at the shoulder: {found[('joint_damping', 'shoulder')].value:.6g} (truth {b})"
    )
    assert abs(quadratic.value - c) <= QUADRATIC_RTOL * c
    linear = found[("joint_damping", "shoulder")]
    assert abs(linear.value - b) <= DAMPING_RTOL * b
    assert linear.ci[0] <= linear.value <= linear.ci[1]
    assert result.before.rollout_rmse_1s > MIN_ROLLOUT_DROP * result.after.rollout_rmse_1s
    # the augmented model holds the effects as cldyn terms
    terms = result.model.dissipation.terms
    assert [type(t) for t in terms if isinstance(t, cldyn.JointQuadraticDamping | cldyn.JointDamping)] in (
        [cldyn.JointDamping, cldyn.JointQuadraticDamping],
        [cldyn.JointQuadraticDamping, cldyn.JointDamping],
    )
    if importlib.util.find_spec("matplotlib") is None:
        return  # the report's plots need the [vision] extra; everything above is checked without it
    out = result.save(tmp_path / "report")
    report = json.loads((out / "report.json").read_text())
    assert {(d["effect"], d["where"]) for d in report["detected"]} == set(found)
    assert set(report["before"]) >= {"accel_rmse", "rollout_rmse_1s"}
    assert (out / "report.md").read_text().startswith("# Missing physics")
    assert (out / "error_over_time.png").stat().st_size > 10_000
    assert (out / "residual_vs_feature.png").stat().st_size > 10_000


@pytest.mark.slow
def test_identify_gives_the_same_damping_at_two_rates():
    # one recording of a damped pendulum at 1 kHz with 1 mm of noise, identified as it is and thinned
    # to 100 Hz: the settings follow the data in seconds, so both find the damping, and the same value
    b = 0.1
    system, joints, fast, coordinates = _reference_data(
        "pendulum", lambda q, qd: -b * qd, runs=16, seconds=3.0, dt=0.001, seed=2
    )
    x = np.asarray(fast.x) + 0.001 * np.random.default_rng(3).standard_normal(fast.x.shape)
    rates = (cldyn.Sequences(x, fast.u, 0.001), cldyn.Sequences(x[:, ::10], fast.u[:, ::10], 0.01))
    values, widths = [], []
    for data in rates:
        result = cldyn.identify(system, data, joint_coordinates=coordinates, joints=joints, bootstrap=30)
        assert [(d.name, d.where) for d in result.detected] == [("joint_damping", "hinge")], result.summary()
        assert result.before.rollout_rmse_1s > MIN_ROLLOUT_DROP * result.after.rollout_rmse_1s
        values.append(result.detected[0].value)
        widths.append(result.settings["smoothing"]["test_width_seconds"])
        print(f"dt {data.dt}: damping {values[-1]:.5g} (truth {b}); {result.settings['seconds']:.1f} s")
    assert all(abs(v - b) <= DAMPING_RATES_RTOL * b for v in values)
    assert abs(values[0] - values[1]) <= RATE_AGREEMENT * values[1]
    assert abs(widths[0] - widths[1]) <= 0.1 * widths[1]


@pytest.mark.slow
def test_identify_reads_fast_turns_sampled_coarsely():
    # the damped acrobot sampled at 20 Hz, its links turning half a radian per sample (95th percentile):
    # smoothed through the joint map's angles, and rolled out in steps of a tenth of the motion's time
    # scale, the damping is read nearly as at 100 Hz
    damping = (0.05, 0.03)
    system, joints, data, coordinates = _reference_data(
        "acrobot", lambda q, qd: -jnp.asarray(damping) * qd, seconds=6.0, dt=0.05, seed=3
    )
    angles = np.unwrap(np.asarray(jax.vmap(jax.vmap(joints.joints))(jnp.asarray(data.x))), axis=1)
    assert np.percentile(np.abs(np.diff(angles, axis=1)), 95) > 0.3  # the premise: fast turns
    result = cldyn.identify(system, data, joint_coordinates=coordinates, joints=joints, bootstrap=30)
    assert result.settings["smoothing"]["rollout_substeps"] > 1
    assert result.before.diverged == 0 and result.after.diverged == 0
    found = {d.where: d.value for d in result.detected if d.name == "joint_damping"}
    assert set(found) == {"shoulder", "elbow"}, result.summary()
    for where, truth in zip(("shoulder", "elbow"), damping):
        assert abs(found[where] - truth) <= FAST_TURNS_RTOL * truth, result.summary()


def test_identify_names_a_residual_of_the_forbidden_sign():
    # a pendulum that gains energy in proportion to its speed (+b qd, integrated by the reference):
    # no damping can explain that, so nothing is detected, and the warning names the negative damping
    b = 0.1
    system, joints, data, coordinates = _reference_data("pendulum", lambda q, qd: b * qd, seed=4)
    result = cldyn.identify(
        system, data, joint_coordinates=coordinates, joints=joints, bootstrap=10, max_rounds=1
    )
    assert result.outcome == "nothing detected" and not result.detected, result.summary()
    (warning,) = [w for w in result.warnings if "asks for" in w]
    named = dict(re.findall(r"(\w+\[hinge\]) = (-?[0-9.e+-]+)", warning))
    assert float(named["joint_damping[hinge]"]) == pytest.approx(-b, rel=DAMPING_RTOL)


def test_identify_says_when_the_data_cannot_support_a_conclusion():
    # four short runs without control: too few equations for a conclusion, and the actuator's gain
    # cannot be examined at all; "nothing could be detected" is not "nothing detected"
    system, joints, data, coordinates = _reference_data("pendulum", runs=4, seconds=0.8, control=0.0)
    result = cldyn.identify(
        system, data, joint_coordinates=coordinates, joints=joints, bootstrap=10, max_rounds=1
    )
    assert result.outcome == "nothing could be detected" and not result.detected
    assert any(p.startswith("too short") for p in result.adequacy.problems), result.adequacy
    assert ("actuator_gain[u0]", "actuator 'u0' is never driven (its control is zero throughout)") in (
        result.adequacy.unexamined
    )
    summary = result.summary()
    assert summary.startswith("nothing could be detected: too short") and "not examined" in summary
    assert result.to_dict()["outcome"] == "nothing could be detected"


@pytest.mark.parametrize("name", ["acrobot", "chain3"])
def test_the_basis_of_the_joint_coordinates_is_the_joint_maps_jacobian(name):
    # without a JointMap, G solves [dq/dx; DPhi] G = [I; 0]: at any pose it equals dF/dq of the
    # chain's forward map (a different computation: autodiff of the joint map), and it moves smoothly
    from cldyn._identify.residual import basis

    system, joints, _ = reference_systems()[name]
    coordinates = tuple(_hinges(joints.num_joints))
    for q in np.random.default_rng(0).uniform(-3, 3, size=(5, joints.num_joints)):
        x = joints.keypoints(jnp.asarray(q))
        np.testing.assert_allclose(basis(system, coordinates, x), basis(system, joints, x), atol=1e-12)
        # its derivative along a motion (which the weak form needs) is the joint map's too
        xd = joints.to_keypoints(jnp.asarray(q), jnp.ones(joints.num_joints))[1]
        rate = [jax.jvp(lambda y, f=f: basis(system, f, y), (x,), (xd,))[1] for f in (coordinates, joints)]
        np.testing.assert_allclose(*rate, atol=1e-10)


def test_identify_without_a_joint_map_finds_the_damping():
    b = 0.1
    system, _, data, coordinates = _reference_data("pendulum", lambda q, qd: -b * qd, runs=12, seed=2)
    result = cldyn.identify(system, data, joint_coordinates=coordinates, bootstrap=20)
    assert [(d.name, d.where) for d in result.detected] == [("joint_damping", "hinge")], result.summary()
    assert abs(result.detected[0].value - b) <= DAMPING_RTOL * b
    # one coordinate per degree of freedom, or the basis is not determined
    with pytest.raises(ValueError, match="2 joint coordinates \\+ 1 constraints != 2"):
        cldyn.identify(system, data, joint_coordinates={**coordinates, "again": coordinates["hinge"]})


def test_identify_refuses_data_that_break_the_model_kinematics():
    system, joints, data, coordinates = _effect_free_pendulum()
    # keypoints of a pendulum 1.3 times as long as the model's (0.7 m): the anchor's distance is off by
    # 0.3 * 0.7 m at every sample
    longer = cldyn.Sequences(1.3 * np.asarray(data.x), data.u, data.dt)
    with pytest.raises(cldyn.ConstraintViolation, match=r"Anchor\(keypoint=0.* by 0\.21 .*holds it at 0\.7,"):
        cldyn.identify(system, longer, joint_coordinates=coordinates, joints=joints)
    # a pivot 0.3 m away from the model's, without a joint map: |x| varies along the runs
    shifted = cldyn.Sequences(np.asarray(data.x) + np.array([0.3, 0.0]), data.u, data.dt)
    radius = np.linalg.norm(np.asarray(shifted.x), axis=-1)
    check = cldyn.check_constraints(system.constraint, shifted.x, noise=0.0, throw=False)
    assert not check.ok and np.isclose(check.deviation[0], np.std(radius), rtol=1e-9)
    with pytest.raises(cldyn.ConstraintViolation, match=f"by {np.std(radius):.3g} "):
        cldyn.identify(system, shifted, joint_coordinates=coordinates)
    # the exact data keep the constraint to rounding
    assert cldyn.check_constraints(system.constraint, data.x, noise=0.0, level=np.array([0.7])).ok


def test_identify_rejects_bad_input():
    system, joints, data, coordinates = _effect_free_pendulum()
    with pytest.raises(ValueError, match=r"x must have shape \(runs, T, 2\)"):
        cldyn.identify(
            system, cldyn.Sequences(data.x[..., :1], data.u, data.dt), joint_coordinates=coordinates
        )
    bad = np.array(data.x)
    bad[2, 10, 0] = np.nan
    with pytest.raises(ValueError, match="x"):
        cldyn.Sequences(bad, data.u, data.dt)
    with pytest.raises(ValueError, match="unknown effect 'magic'"):
        cldyn.identify(system, data, joint_coordinates=coordinates, effects=("magic",))
    with pytest.raises(ValueError, match="more than once"):
        cldyn.identify(
            system, data, joint_coordinates=coordinates, effects=("joint_damping", "joint_damping")
        )
    with pytest.raises(ValueError, match="at least 4 runs"):
        cldyn.identify(system, data.take(slice(0, 3)), joint_coordinates=coordinates)
    with pytest.raises(ValueError, match="holdout"):
        cldyn.identify(system, data, joint_coordinates=coordinates, holdout=1.5)
    with pytest.raises(TypeError, match="Sequences"):
        cldyn.identify(system, np.asarray(data.x), joint_coordinates=coordinates)



@pytest.mark.parametrize("potential", [True, False])
def test_refit_holds_the_potential_when_asked(potential):
    """`refit_potential=False` (what keyvision uses for a learnt potential): the dissipation is free in
    the refit, the potential only when asked, the mass never."""
    import equinox as eqx

    from cldyn._identify.refit import _refit_filter

    system, _ = cldyn.systems.pendulum()
    damping = cldyn.JointDamping([cldyn.HingeAngle(child=(None, 0))], jnp.asarray([0.1]))
    damped = eqx.tree_at(lambda s: s.dissipation, system, damping, is_leaf=lambda v: v is None)
    spec = _refit_filter(damped, potential)
    free = lambda part: any(jax.tree.leaves(part))
    assert free(spec.dissipation)
    assert free(spec.potential) is potential
    assert not free(spec.mass)
