"""Losses (eq. 11-13, rollouts, inverse dynamics) on exact data of independent references.

The data come from the generalised-coordinate references of `tests/helpers.py` (link angles, centre
of mass velocities, rotational inertia; no cldyn code), integrated finely, or from closed forms.
The models under test are cldyn's analytic systems with the same physical parameters.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import euler_lagrange_acceleration, keypoint_state, reference_systems

import cldyn

ORDER_TOL = 0.5  # on the slope of log(loss) vs log(h)
EXACT_ATOL = 1e-18  # the inverse-dynamics loss on exact states, (m/s^2)^2
CLOSED_FORM_RTOL = 1e-9
FINE_DT = 0.005  # the reference's sampling interval; coarser data take every 2nd and 4th sample


# classic RK4 as stages (offset, weight) in one loop, so the reference's dynamics compile once
_RK4_STAGES = jnp.array([[0.0, 1.0], [0.5, 2.0], [0.5, 2.0], [1.0, 1.0]])


def _reference_runs(reference, q0s, us, dt, samples, *, substeps=8):
    """Keypoint positions, velocities and accelerations `(runs, samples, k)` of the reference,
    integrated by classic RK4 in its joint coordinates with each run's constant control."""
    h = dt / substeps

    def one(q0, u):
        def rate(q, qd):
            return qd, euler_lagrange_acceleration(reference, q, qd, u)

        def substep(state, _):
            def stage(carry, coefficients):
                k, total = carry
                k = rate(*(s + coefficients[0] * h * r for s, r in zip(state, k)))
                return (k, tuple(t + coefficients[1] * r for t, r in zip(total, k))), None

            zeros = tuple(jnp.zeros_like(s) for s in state)
            (_, total), _ = jax.lax.scan(stage, (zeros, zeros), _RK4_STAGES)
            return tuple(s + h / 6 * t for s, t in zip(state, total)), None

        def sample(state, _):
            new, _ = jax.lax.scan(substep, state, None, length=substeps)
            return new, state

        _, (q, qd) = jax.lax.scan(sample, (q0, jnp.zeros_like(q0)), None, length=samples)
        qdd = jax.vmap(lambda a, b: euler_lagrange_acceleration(reference, a, b, u))(q, qd)
        return jax.vmap(lambda a, b, c: keypoint_state(reference, a, b, c))(q, qd, qdd)

    x, xd, xdd = jax.jit(jax.vmap(one))(q0s, us)
    return cldyn.Sequences(x, us, dt, xd=xd, xdd=xdd)


@eqx.filter_jit
def _value(loss, model, data):
    return loss(model, data)


@pytest.fixture(scope="module")
def acrobot():
    """The acrobot of `reference_systems` (unequal, off-axis links, both joints actuated) and three
    runs of its reference sampled every 5 ms."""
    system, _, reference = reference_systems()["acrobot"]
    q0s = jnp.array([[1.0, -0.5], [2.0, 0.3], [-1.5, 1.0]])
    us = jnp.array([[0.3, -0.2], [0.0, 0.0], [-0.5, 0.4]])
    return system, _reference_runs(reference, q0s, us, FINE_DT, 61)


@pytest.fixture(scope="module")
def pendulum():
    """The pendulum of `reference_systems` (a rigid body with its centre of mass off the rod) and
    four runs of its reference sampled every 5 ms."""
    system, _, reference = reference_systems()["pendulum"]
    q0s = jnp.array([[2.0], [-1.0], [0.5], [2.8]])
    us = jnp.array([[0.5], [0.0], [-1.0], [0.2]])
    return system, _reference_runs(reference, q0s, us, FINE_DT, 41)


def _every(data, every, samples=None):
    """Every `every`-th sample (interval `every * dt`), without the measured derivatives."""
    stop = None if samples is None else every * (samples - 1) + 1
    return cldyn.Sequences(data.x[:, :stop:every], data.u[:, :stop:every], data.dt * every)


def _slope(every, values):
    return np.polyfit(np.log(every), np.log(values), 1)[0]


@pytest.mark.parametrize("project, order", [(False, 2), (True, 2), (False, 4)])
def test_collocation_vanishes_at_the_order_of_its_stencils(acrobot, project, order):
    system, data = acrobot
    every = np.array([4, 2, 1])
    loss = cldyn.Collocation(project=project, order=order)
    values = [float(_value(loss, system, _every(data, e))) for e in every]
    # the stencils' residual is O(h^order), the loss its square: O(h^(2 order))
    assert abs(_slope(every, values) - 2 * order) < ORDER_TOL * order / 2, values


@pytest.mark.slow
def test_rollout_losses_vanish_as_the_interval_shrinks(pendulum):
    system, data = pendulum
    every = np.array([4, 2])
    losses = (cldyn.Rollout(steps=3, solver=cldyn.RK4()), cldyn.MultipleShooting(segment=4))
    values = np.array([[float(_value(loss, system, _every(data, e, 11))) for loss in losses] for e in every])
    # starts carry the central difference's O(h^2) velocity error: positions are off by O(h^3) after
    # a fixed number of steps, and the loss (divided by h^4) falls as h^2 at least
    for column in values.T:
        assert _slope(every, column) > 2 - ORDER_TOL, values


def test_euler_rollout_matches_its_closed_form():
    # a free particle in uniform gravity: central differences are exact on parabolas, and n explicit
    # Euler steps fall short of the parabola by g n h^2 / 2
    g, h, n = 9.81, 0.05, 4
    model = cldyn.ConstrainedLagrangian(
        mass=cldyn.PointMasses(jnp.array([2.0])), potential=cldyn.Gravity.from_masses(jnp.array([2.0]), g=g)
    )
    t = h * jnp.arange(12.0)
    x = jnp.stack([0.3 * t, 1.0 + 0.5 * t - 0.5 * g * t**2], axis=-1)[None]
    data = cldyn.Sequences(x, None, h)
    expected = g**2 * np.mean(np.arange(1, n + 1) ** 2) / 4
    assert float(_value(cldyn.Rollout(steps=n), model, data)) == pytest.approx(expected, rel=CLOSED_FORM_RTOL)
    assert float(_value(cldyn.Collocation(), model, data)) < EXACT_ATOL


def test_inverse_dynamics_vanishes_on_exact_states_of_the_reference(acrobot):
    system, data = acrobot
    assert float(_value(cldyn.InverseDynamics(), system, data)) < EXACT_ATOL
    assert float(_value(cldyn.InverseDynamics(project=True), system, data)) < EXACT_ATOL
    # with central-difference velocities the residual is O(h^2), the loss O(h^4)
    every = np.array([4, 2, 1])
    values = [
        float(
            _value(
                cldyn.InverseDynamics(),
                system,
                cldyn.Sequences(data.x[:, ::e], data.u[:, ::e], data.dt * e, xdd=data.xdd[:, ::e]),
            )
        )
        for e in every
    ]
    assert abs(_slope(every, values) - 4) < ORDER_TOL, values
    # a model with another gear is not exact
    wrong = eqx.tree_at(lambda s: s.input_matrix.gears, system, 1.1 * system.input_matrix.gears)
    assert float(_value(cldyn.InverseDynamics(), wrong, data)) > 1e6 * EXACT_ATOL
    with pytest.raises(ValueError, match="needs measured accelerations"):
        cldyn.InverseDynamics()(system, cldyn.Sequences(data.x, data.u, data.dt))


def test_losses_combine_and_check_their_inputs(acrobot):
    system, data = acrobot
    combined = cldyn.Collocation() + 0.5 * cldyn.InverseDynamics()
    assert isinstance(combined, cldyn.LossSum) and len(combined.terms) == 2
    assert [w for w, _ in (2 * combined).terms] == [2.0, 1.0]
    data = _every(data, 4)
    data = cldyn.Sequences(data.x, data.u, data.dt, xdd=data.x[:, ::-1])  # any accelerations
    expected = _value(cldyn.Collocation(), system, data) + 0.5 * _value(cldyn.InverseDynamics(), system, data)
    assert float(_value(combined, system, data)) == pytest.approx(float(expected), rel=CLOSED_FORM_RTOL)
    short = cldyn.Sequences(data.x[:, :4], data.u[:, :4], data.dt)
    with pytest.raises(ValueError, match="at least 5 samples"):
        cldyn.Collocation()(system, short)
    wrong = cldyn.Sequences(jnp.zeros((2, 8, 2)), jnp.zeros((2, 2)), 0.1)
    with pytest.raises(ValueError, match="the model has k=4"):
        cldyn.Collocation()(system, wrong)
    with pytest.raises(ValueError, match="order must be 2 or 4"):
        cldyn.Collocation(order=3)
    with pytest.raises(ValueError, match="steps >= 1"):
        cldyn.Rollout(steps=0)
    with pytest.raises(ValueError, match="segment >= 1"):
        cldyn.MultipleShooting(segment=0)


@pytest.mark.parametrize(
    "kind, loss",
    [
        ("keycld", cldyn.Collocation(project=True)),
        ("keycld", cldyn.Rollout(steps=2)),
        pytest.param("keycld", cldyn.MultipleShooting(segment=4), marks=pytest.mark.slow),
        ("nc", cldyn.Collocation()),
        pytest.param("node2", cldyn.Rollout(steps=2, solver=cldyn.RK4()), marks=pytest.mark.slow),
    ],
    ids=["keycld-collocation", "keycld-rollout", "keycld-shooting", "nc-collocation", "node2-rollout-rk4"],
)
def test_losses_differentiate_for_every_model(pendulum, kind, loss):
    _, data = pendulum
    data = cldyn.Sequences(data.x[:2, :12], data.u[:2, :12], data.dt)
    key = jax.random.key(0)
    if kind == "node2":
        model = cldyn.SecondOrderNeuralODE(2, 1, key=key)
    else:
        model = cldyn.keycld_model(2, 1, cldyn.Anchor(0) if kind == "keycld" else None, key=key)
    value, grads = eqx.filter_jit(eqx.filter_value_and_grad(loss))(model, data)
    leaves = jax.tree.leaves(grads)
    assert np.isfinite(float(value)) and leaves
    assert all(np.all(np.isfinite(np.asarray(g))) for g in leaves)
