"""The held-control rollout against closed forms, evaluation metrics against hand-computed cases,
and `evaluate` on an exact and a wrong model."""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn

TOL = 1e-12
# A free point mass under a held force moves on exact parabolas, which RK4 integrates exactly.
PARABOLA_ATOL = 1e-12
FLOAT32_ATOL = 1e-6  # a few float32 ulps of positions of order 1
# Small-angle pendulum (theta0 = 1e-3 rad) against theta0 cos(omega t): the nonlinearity shifts the
# phase by theta0^2 / 16 * omega t ~ 6e-7 and RK4 (h = 0.01) by ~3e-7, relative to the amplitude.
SMALL_ANGLE_RTOL = 1e-5
GRAVITY = 9.81


def _free_point_mass(mass: float) -> cldyn.ConstrainedLagrangian:
    """One planar point mass, no potential, no constraint, a force on each axis: xdd = u / m."""
    return cldyn.ConstrainedLagrangian(
        mass=cldyn.PointMasses(jnp.array([mass])), input_matrix=cldyn.ConstantInput(jnp.eye(2))
    )


def _held_motion(x0, v0, controls, mass, h):
    """The exact motion under controls held over each interval: a parabola per interval."""
    x, v, out = np.array(x0, float), np.array(v0, float), [np.array(x0, float)]
    for u in controls[:-1]:
        a = np.asarray(u) / mass
        x, v = x + v * h + a * h**2 / 2, v + a * h
        out.append(x)
    return np.array(out)


def test_rollout_of_a_constant_force_is_a_parabola():
    mass, h = 2.0, 0.1
    controls = np.tile([1.5, -0.5], (11, 1))
    run = cldyn.rollout(_free_point_mass(mass), [0.3, -0.1], [0.5, 0.2], controls, h)
    np.testing.assert_allclose(run.ts, h * np.arange(11), rtol=0, atol=TOL)
    t = h * np.arange(11)[:, None]
    exact = np.array([0.3, -0.1]) + np.array([0.5, 0.2]) * t + np.array([1.5, -0.5]) / mass * t**2 / 2
    np.testing.assert_allclose(run.x, exact, rtol=0, atol=PARABOLA_ATOL)
    np.testing.assert_allclose(run.xd[-1], [0.5 + 1.5 / mass, 0.2 - 0.5 / mass], rtol=0, atol=PARABOLA_ATOL)
    assert run.result == dfx.RESULTS.successful


@pytest.mark.parametrize("substeps", [1, 3])
def test_rollout_holds_each_control_over_its_interval(substeps):
    mass, h = 2.0, 0.1
    controls = np.array([[1.0, -2.0], [3.0, 0.5], [-1.0, 1.0], [0.0, 4.0], [2.0, 2.0]])
    x0, v0 = np.array([0.3, -0.1]), np.array([0.5, 0.2])
    run = cldyn.rollout(_free_point_mass(mass), x0, v0, controls, h, dt0=h / substeps)
    np.testing.assert_allclose(run.x, _held_motion(x0, v0, controls, mass, h), rtol=0, atol=PARABOLA_ATOL)


@pytest.mark.parametrize(
    "solver, dt0",
    [(cldyn.RK4(), 0.03), (dfx.Tsit5(), None), (cldyn.RATTLE(), 0.07)],
    ids=["rk4-unaligned-steps", "tsit5-adaptive", "rattle-unaligned-steps"],
)
def test_simulate_holds_each_sample_whatever_the_steps(solver, dt0):
    # steps that do not line up with the samples (or adaptive ones) still hold each sample over its
    # own interval: simulate steps onto the jumps of the hold
    mass, h = 2.0, 0.1
    controls = np.array([[1.0, -2.0], [3.0, 0.5], [-1.0, 1.0], [0.0, 4.0], [2.0, 2.0]])
    x0, v0 = np.array([0.3, -0.1]), np.array([0.5, 0.2])
    ts = np.linspace(0.0, 0.4, 9)  # saves between the samples too
    hold = cldyn.ZeroOrderHold(jnp.asarray(controls), dt=h)
    stabilisation = None if isinstance(solver, cldyn.RATTLE) else cldyn.Projection()
    traj = cldyn.simulate(
        _free_point_mass(mass), x0, v0, ts, control=hold, solver=solver, dt0=dt0, stabilisation=stabilisation
    )
    fine = np.repeat(controls, 2, axis=0)[:-1]  # each sample held over two half intervals
    exact = _held_motion(x0, v0, fine, mass, h / 2)
    np.testing.assert_allclose(traj.x, exact, rtol=0, atol=1e-9)


def test_forward_mode_derivative_of_a_held_rollout_matches_the_parabola():
    # identify differentiates rollouts in forward mode: the held control must not put diffrax's
    # reverse-mode-only loop in the way. d x(T) / d v0 of a free mass is T, per axis.
    mass, h = 2.0, 0.1
    controls = np.array([[1.0, -2.0], [3.0, 0.5], [-1.0, 1.0]])

    def final(v0):
        run = cldyn.rollout(_free_point_mass(mass), jnp.array([0.3, -0.1]), v0, controls, h,
                            adjoint=dfx.ForwardMode())
        return run.x[-1]

    jacobian = jax.jacfwd(final)(jnp.array([0.5, 0.2]))
    np.testing.assert_allclose(jacobian, 2 * h * np.eye(2), rtol=0, atol=PARABOLA_ATOL)


def test_a_float32_model_rolls_out_in_float32():
    # the save times follow the state's precision (strict dtype promotion refuses a float64 grid)
    mass, h = 2.0, 0.1
    model = jax.tree.map(
        lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, _free_point_mass(mass)
    )
    controls = np.array([[1.0, -2.0], [3.0, 0.5], [-1.0, 1.0]])
    x0, v0 = np.array([0.3, -0.1], np.float32), np.array([0.5, 0.2], np.float32)
    run = cldyn.rollout(model, x0, v0, controls, h)
    assert run.x.dtype == jnp.float32 and run.ts.dtype == jnp.float32
    np.testing.assert_allclose(run.x, _held_motion(x0, v0, controls, mass, h), rtol=0, atol=FLOAT32_ATOL)


def test_rollout_of_a_small_angle_pendulum_is_harmonic():
    length, theta0, h, samples = 0.5, 1e-3, 0.01, 201
    system, _ = cldyn.systems.pendulum(mass=1.0, length=length, gravity=GRAVITY)
    x0 = length * np.array([np.sin(theta0), -np.cos(theta0)])  # the angle from straight down
    run = cldyn.rollout(system, x0, np.zeros(2), np.zeros((samples, 1)), h)
    t = h * np.arange(samples)
    theta = theta0 * np.cos(np.sqrt(GRAVITY / length) * t)
    amplitude = length * theta0
    assert np.max(np.abs(run.x[:, 0] - length * np.sin(theta))) < SMALL_ANGLE_RTOL * amplitude
    assert np.max(np.abs(run.x[:, 1] + length * np.cos(theta))) < SMALL_ANGLE_RTOL * amplitude
    # a quarter period in, the bob passes the bottom: the test would see a wrong frequency
    assert np.min(np.abs(run.x[:, 0])) < 0.05 * amplitude


def test_rollout_refuses_bad_arguments():
    model = _free_point_mass(1.0)
    with pytest.raises(ValueError, match="controls must have shape"):
        cldyn.rollout(model, np.zeros(2), np.zeros(2), np.zeros(2), 0.1)
    with pytest.raises(ValueError, match="controls must have shape"):
        cldyn.rollout(model, np.zeros(2), np.zeros(2), np.zeros((1, 2)), 0.1)
    for dt in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="dt must be a positive"):
            cldyn.rollout(model, np.zeros(2), np.zeros(2), np.zeros((3, 2)), dt)


def _ramp_error(errors):
    """Predicted/true trajectories of one planar keypoint whose error is `errors` along x."""
    errors = np.asarray(errors, dtype=float)
    truth = np.zeros((len(errors), 2))
    return truth + np.stack([errors, np.zeros_like(errors)], axis=1), truth


def test_keypoint_error_is_the_worst_keypoint():
    truth = np.zeros((1, 4))
    predicted = np.array([[3.0, 4.0, 0.0, 1.0]])
    np.testing.assert_allclose(cldyn.keypoint_error(predicted, truth), [5.0])


def test_valid_prediction_time_by_hand():
    predicted, truth = _ramp_error([0.0, 0.05, 0.2, 0.01, 0.5])
    # the first sample above 0.1 is index 2: two valid samples out of five
    assert float(cldyn.valid_prediction_time(predicted, truth, threshold=0.1)) == pytest.approx(0.4)
    assert float(cldyn.valid_prediction_time(predicted, truth, threshold=0.1, dt=0.5)) == pytest.approx(1.0)
    assert float(cldyn.valid_prediction_time(predicted, truth, threshold=1.0)) == 1.0
    assert float(cldyn.valid_prediction_time(predicted, truth, threshold=1e-3)) == pytest.approx(0.2)
    batch = cldyn.valid_prediction_time(np.stack([predicted, truth]), np.stack([truth, truth]), threshold=0.1)
    np.testing.assert_allclose(batch, [0.4, 1.0])
    # two keypoints: the worst one counts (here the second crosses 0.1 first, at sample 1)
    two = np.zeros((3, 4))
    two[:, 0] = [0.0, 0.05, 0.5]
    two[:, 3] = [0.0, 0.2, 0.0]
    assert float(cldyn.valid_prediction_time(two, np.zeros((3, 4)), threshold=0.1)) == pytest.approx(1 / 3)
    # a prediction that failed (NaN from sample 3 on, errors below the threshold before): not valid there
    failed = predicted.copy()
    failed[3:] = np.nan
    assert float(cldyn.valid_prediction_time(failed, truth, threshold=1.0)) == pytest.approx(0.6)
    with pytest.raises(ValueError, match="threshold must be positive"):
        cldyn.valid_prediction_time(predicted, truth, threshold=0.0)
    # a shape mismatch: jaxtyping's check in tests, a ValueError otherwise
    with pytest.raises((ValueError, TypeError)):
        cldyn.valid_prediction_time(predicted, truth[:3], threshold=0.1)


def test_relative_error_and_its_geometric_mean_by_hand():
    truth = np.array([[1.0, 0.0], [0.0, 2.0]])
    predicted = np.array([[1.0, 0.0], [0.0, 1.0]])
    # |a - b| / (|a| + |b|): 0 at the first sample, 1 / 3 at the second
    np.testing.assert_allclose(cldyn.relative_error(predicted, truth), [0.0, 1 / 3], atol=TOL)
    predicted = np.array([[2.0, 0.0], [0.0, 1.0]])
    expected = np.sqrt((1 / 3) * (1 / 3))
    assert float(cldyn.geometric_mean_relative_error(predicted, truth)) == pytest.approx(expected)
    exact = cldyn.geometric_mean_relative_error(truth, truth)
    assert float(exact) == pytest.approx(1e-12)


def test_range_of_motion():
    x = np.zeros((2, 3, 4))
    x[0, 1, 2] = 1.5
    x[1, 2, 2] = -0.5
    x[1, 0, 1] = 0.7
    assert cldyn.range_of_motion(x) == pytest.approx(2.0)


@pytest.fixture(scope="module")
def pendulum_runs():
    system, joints = cldyn.systems.pendulum(mass=1.0, length=0.5, gear=1.0)
    h = 0.02

    def one(q0, u):
        x0, xd0 = joints.to_keypoints(q0, jnp.zeros(1))
        ts = h * jnp.arange(30.0)
        return cldyn.simulate(system, x0, xd0, ts, control=u, solver=cldyn.RK4(), dt0=h / 8).x

    q0s = jnp.array([[0.5], [2.0], [-1.0]])
    us = jnp.array([[0.0], [0.3], [0.0]])
    return system, cldyn.Sequences(jax.vmap(one)(q0s, us), us, h)


def test_evaluate_the_exact_model(pendulum_runs):
    system, data = pendulum_runs
    result = cldyn.evaluate(system, data, threshold=0.01)
    assert result.x.shape == (3, 29, 2) and result.ts.shape == (29,)
    np.testing.assert_array_equal(result.vpt, np.ones(3))
    np.testing.assert_allclose(result.vpt_seconds, 28 * 0.02)
    # only the central-difference estimate of the initial velocity separates it from the truth
    assert float(np.max(result.error)) < 1e-3
    assert np.all(result.error_over(0.2) < 1e-3) and np.all(result.gmre < 1e-3)
    # the unforced runs conserve the model's energy along its own rollout
    for run in (0, 2):
        assert np.ptp(result.energy[run]) < 1e-4 * np.abs(result.energy[run]).max()
    summary = result.summary()
    assert summary["vpt"] == 1.0 and summary["runs"] == 3
    short = cldyn.evaluate(system, data, threshold=0.01, horizon=5)
    assert short.x.shape == (3, 6, 2)
    with pytest.raises(ValueError, match="horizon must be between"):
        cldyn.evaluate(system, data, threshold=0.01, horizon=40)


def test_a_rollout_that_fails_is_scored_from_the_failure_on():
    # the exact acrobot driven by an elbow torque of 1e9 (from the sixth sample) leaves its
    # constraints further than one projection brings it back: the run is marked failed, NaN from the
    # failing step on (its state is off the constraints), its VPT ending there; the same run without
    # the torque is predicted to its end
    system, joints = cldyn.systems.acrobot()
    h = 0.01
    x0, xd0 = joints.to_keypoints(jnp.array([0.3, -0.2]), jnp.zeros(2))
    x = cldyn.simulate(system, x0, xd0, h * jnp.arange(12.0), solver=cldyn.RK4(), dt0=h).x
    controls = np.zeros((2, 12, 1))
    controls[1, 6:] = 1e9  # from the sixth sample on
    data = cldyn.Sequences(jnp.stack([x, x]), controls, h)
    # a threshold beyond any distance within the arms' reach: only the failure ends a VPT
    result = cldyn.evaluate(system, data, threshold=10.0)
    np.testing.assert_array_equal(result.failed, [False, True])
    finite = np.all(np.isfinite(result.x[1]), axis=-1)
    first = int(np.argmin(finite))  # the first sample of the failed run that is NaN
    assert 6 <= first and finite[:first].all() and np.isnan(result.x[1, first:]).all()
    assert result.vpt[0] == 1.0 and result.vpt[1] == pytest.approx((first - 1) / 10)
    summary = result.summary()
    assert summary["failed_runs"] == 1 and summary["vpt"] == pytest.approx((1.0 + (first - 1) / 10) / 2)
    # the failed run has no error to average: the errors are those of the run that completed, which
    # follows the exact model's own simulation to the central difference's error of its start
    assert np.isfinite(summary["gmre"]) and summary["gmre"] == pytest.approx(result.gmre[0])
    assert summary["final_error"] == pytest.approx(result.error[0, -1]) and 0 <= summary["final_error"] < 1e-3


def test_evaluate_a_wrong_model_has_a_short_vpt(pendulum_runs):
    system, data = pendulum_runs
    wrong = cldyn.ConstrainedLagrangian(
        mass=system.mass, potential=cldyn.Gravity(3 * system.potential.weights), constraint=system.constraint,
        input_matrix=system.input_matrix,
    )
    result = cldyn.evaluate(wrong, data, threshold=0.01)
    assert float(np.mean(result.vpt)) < 0.8
    node2 = cldyn.SecondOrderNeuralODE(2, 1, key=jax.random.key(0))
    assert cldyn.evaluate(node2, data, threshold=0.01).energy is None
