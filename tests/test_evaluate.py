"""Evaluation metrics against hand-computed cases, and `evaluate` on an exact model."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn

TOL = 1e-12


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
        return cldyn.simulate(system, x0, xd0, h * jnp.arange(30.0), control=u, solver=cldyn.RK4(), dt0=h / 8).x

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
