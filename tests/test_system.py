"""The constrained Euler-Lagrange equations (eq. 6) against independent mechanics."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    ChainReference,
    euler_lagrange_acceleration,
    joint_acceleration,
    keypoint_state,
    reference_energy,
    reference_systems,
)

import cldyn

N_STATES = 100
ACCEL_RTOL = 1e-9
CONSTRAINT_TOL = 1e-10
POWER_RTOL = 1e-10
FORCE_RTOL = 1e-10
ENERGY_ATOL = 1e-10
# closed forms and identities evaluated in float64
EXACT_RTOL = 1e-12
EXACT_ATOL = 1e-12
NEWTON_RTOL = 1e-14
# a duplicated constraint: the unrolled solve's zero pivot, and lineax's SVD for the multipliers
REDUNDANT_RTOL = 1e-8
REDUNDANT_ATOL = 1e-10
SHARE_RTOL = 1e-6
SHARE_ATOL = 1e-9

CASES = reference_systems()


def _random_joint_states(key, m, num_inputs, n=N_STATES):
    kq, kqd, ku = jax.random.split(key, 3)
    q = jax.random.uniform(kq, (n, m), minval=-np.pi, maxval=np.pi)
    qd = jax.random.normal(kqd, (n, m)) * 2.0
    u = jax.random.normal(ku, (n, num_inputs))
    return q, qd, u


@pytest.mark.parametrize("name", sorted(CASES))
def test_acceleration_matches_generalized_coordinates(name):
    system, _, reference = CASES[name]
    m = reference.n if hasattr(reference, "n") else 2
    q, qd, u = _random_joint_states(jax.random.key(0), m, system.num_inputs)

    @jax.jit
    @jax.vmap
    def compare(q, qd, u):
        qdd = euler_lagrange_acceleration(reference, q, qd, u)
        x, xd, xdd_ref = keypoint_state(reference, q, qd, qdd)
        return system.acceleration(x, xd, u), xdd_ref

    xdd, xdd_ref = compare(q, qd, u)
    scale = jnp.max(jnp.abs(xdd_ref), axis=1, keepdims=True)
    rel = np.asarray(jnp.max(jnp.abs(xdd - xdd_ref) / scale, axis=1))
    assert rel.shape == (N_STATES,)
    assert rel.max() < ACCEL_RTOL, f"{name}: worst relative error {rel.max():.2e}"


def _keypoint_states(name, key):
    system, _, reference = CASES[name]
    m = reference.n if hasattr(reference, "n") else 2
    q, qd, u = _random_joint_states(key, m, system.num_inputs)
    x, xd = jax.jit(jax.vmap(lambda q, qd: keypoint_state(reference, q, qd)))(q, qd)
    return system, x, xd, u


@pytest.mark.parametrize("name", sorted(CASES))
def test_constraints_hold_to_second_order(name):
    system, x, xd, u = _keypoint_states(name, jax.random.key(1))

    @jax.jit
    @jax.vmap
    def residual(x, xd, u):
        xdd = system.acceleration(x, xd, u)
        # second derivative of Phi along the motion, with the Hessian formed explicitly here
        hess = jax.hessian(system.constraint)(x)
        return system.constraint.jacobian(x) @ xdd + jnp.einsum("nij,i,j->n", hess, xd, xd)

    assert float(jnp.max(jnp.abs(residual(x, xd, u)))) < CONSTRAINT_TOL


# Point masses on massless rods (KeyCLD's model, eq. 14): the constraint forces are the rod forces,
# and Newton's law for each mass with the reference's accelerations gives them independently.
POINT_CHAINS = {
    "pendulum": ((1.3,), (0.7,)),
    "double": ((1.0, 0.6), (1.0, 0.8)),
    "chain3": ((1.0, 2.0, 0.7), (1.0, 0.5, 0.8)),
}
GRAVITY = 9.81


def _point_chain(masses, lengths):
    n = len(masses)
    system = cldyn.ConstrainedLagrangian(
        mass=cldyn.PointMasses(jnp.array(masses)),
        potential=cldyn.Gravity.from_masses(jnp.array(masses), g=GRAVITY),
        constraint=cldyn.Stack([cldyn.Anchor(0)] + [cldyn.Distance(i - 1, i) for i in range(1, n)]),
    )
    reference = ChainReference(
        masses, lengths, coms=lengths, offsets=(0.0,) * n, inertias=(0.0,) * n, gravity=GRAVITY
    )
    return system, reference


def _rod_forces(masses, x, xdd):
    """Newton-Euler for each point mass, from the tip inwards: `(keypoint forces, tensions, shear)`.

    The rods push and pull each mass with `m_i (a_i + g e_y)`. Rod `i` (from keypoint `i-1`, or the
    pivot, to keypoint `i`) acts on mass `i` with `lambda_i e_i` and on mass `i-1` with the opposite, so
    the tension of each rod follows from the tip inwards. Massless rods carry no shear: the component
    across the rod is returned as a check on the reference.
    """
    points, acc = x.reshape(-1, 2), xdd.reshape(-1, 2)
    n = len(masses)
    forces = jnp.stack([masses[i] * (acc[i] + jnp.array([0.0, GRAVITY])) for i in range(n)])
    tensions, shear, from_child = [None] * n, [None] * n, jnp.zeros(2)
    for i in reversed(range(n)):
        rod = points[i] - (points[i - 1] if i > 0 else jnp.zeros(2))
        unit = rod / jnp.linalg.norm(rod)
        own = forces[i] - from_child  # what rod i exerts on mass i
        tensions[i] = jnp.dot(own, unit)
        shear[i] = own[0] * unit[1] - own[1] * unit[0]
        from_child = -tensions[i] * unit
    return forces.reshape(-1), jnp.stack(tensions), jnp.stack(shear)


@pytest.mark.parametrize("angle", [0.3, -1.1])
def test_a_body_on_an_inclined_rail_slides_at_g_sin_theta(angle):
    # two point masses tied rigidly (two linear rows: a body that does not turn), the first on a rail
    # at `angle` (one row, the rail's normal): frictionless, the body accelerates along the rail at
    # g sin(angle) downhill and the rail pushes along its normal with the weight's normal part
    masses = jnp.array([1.0, 0.4])
    along, normal = np.array([np.cos(angle), np.sin(angle)]), np.array([-np.sin(angle), np.cos(angle)])
    rows = [[*normal, 0.0, 0.0], [1.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, -1.0]]
    system = cldyn.ConstrainedLagrangian(
        mass=cldyn.PointMasses(masses),
        potential=cldyn.Gravity.from_masses(masses, g=GRAVITY),
        constraint=cldyn.LinearConstraint(rows),
    )
    x = jnp.array([0.3, 0.3 * np.tan(angle), 0.5, -0.2])
    xd = jnp.asarray(np.tile(1.7 * along, 2))
    expected = np.tile(-GRAVITY * np.sin(angle) * along, 2)
    np.testing.assert_allclose(system.acceleration(x, xd), expected, rtol=EXACT_RTOL, atol=EXACT_ATOL)
    force = np.asarray(system.constraint_force(x, xd)).reshape(2, 2).sum(axis=0)  # on the body
    weight = float(masses.sum()) * GRAVITY
    np.testing.assert_allclose(force, weight * np.cos(angle) * normal, rtol=EXACT_RTOL, atol=EXACT_ATOL)
    # the rail is geometry, not a parameter: training a model does not move it (the masses it does)
    def loss(model):
        return jnp.sum(model.acceleration(x, xd) ** 2) + jnp.sum(model.constraint_force(x, xd) ** 2)

    grads = eqx.filter_grad(loss)(system)
    assert np.all(np.asarray(grads.constraint.rows) == 0) and np.any(np.asarray(grads.mass.sqrt_masses) != 0)


@pytest.mark.parametrize("name", sorted(POINT_CHAINS))
def test_constraint_forces_are_the_rod_forces_of_newton_euler(name):
    masses, lengths = POINT_CHAINS[name]
    system, reference = _point_chain(masses, lengths)
    q, qd, _ = _random_joint_states(jax.random.key(2), len(masses), 0)

    @jax.jit
    @jax.vmap
    def compare(q, qd):
        qdd = euler_lagrange_acceleration(reference, q, qd, jnp.zeros(0))
        x, xd, xdd = keypoint_state(reference, q, qd, qdd)
        forces, tensions, shear = _rod_forces(masses, x, xdd)
        return system.constraint_force(x, xd), system.multipliers(x, xd), forces, tensions, shear

    force, lam, force_ref, lam_ref, shear = compare(q, qd)
    scale = float(jnp.max(jnp.abs(force_ref)))
    assert float(jnp.max(jnp.abs(shear))) < FORCE_RTOL * scale  # the reference is consistent
    assert float(jnp.max(jnp.abs(force - force_ref))) < FORCE_RTOL * scale
    assert float(jnp.max(jnp.abs(lam - lam_ref))) < FORCE_RTOL * scale


@pytest.mark.parametrize("name", sorted(CASES))
def test_constraint_force_does_no_work(name):
    system, x, xd, u = _keypoint_states(name, jax.random.key(2))
    force = jax.jit(jax.vmap(system.constraint_force))(x, xd, u)
    power = jnp.sum(force * xd, axis=1)
    scale = jnp.linalg.norm(force, axis=1) * jnp.linalg.norm(xd, axis=1)
    assert float(jnp.max(jnp.abs(power) / scale)) < POWER_RTOL


@pytest.mark.parametrize("name", sorted(CASES))
def test_power_balance_of_the_reference_energy(name):
    """Along cldyn's accelerations the reference's own energy changes by the input power `qd . Q`."""
    system, _, reference = CASES[name]
    m = reference.n if hasattr(reference, "n") else 2
    q, qd, u = _random_joint_states(jax.random.key(3), m, system.num_inputs)

    @jax.jit
    @jax.vmap
    def balance(q, qd, u):
        x, xd = keypoint_state(reference, q, qd)
        qdd = joint_acceleration(reference, q, qd, system.acceleration(x, xd, u))
        energy = lambda q_, qd_: reference_energy(reference, q_, qd_)
        by_position = jax.jvp(lambda q_: energy(q_, qd), (q,), (qd,))[1]
        by_velocity = jax.jvp(lambda qd_: energy(q, qd_), (qd,), (qdd,))[1]
        input_power = jnp.dot(qd, reference.generalized_force(q, u))
        return (
            by_position + by_velocity,
            input_power,
            jnp.abs(by_position) + jnp.abs(by_velocity) + jnp.abs(input_power),
            system.power(x, xd, u),
            system.energy(x, xd) - energy(q, qd),
        )

    de_dt, input_power, scale, power, offset = balance(q, qd, u)
    assert float(jnp.max(jnp.abs(de_dt - input_power) / scale)) < POWER_RTOL
    assert float(jnp.max(jnp.abs(power - input_power) / scale)) < POWER_RTOL
    # cldyn's energy is the reference's, up to the constant of the potential's origin
    assert float(jnp.max(jnp.abs(offset - offset[0]))) < ENERGY_ATOL


def test_armature_matches_the_reference_with_rotor_inertia():
    """Rotor inertia `1/2 a_j qd_j^2` on each relative joint angle of an acrobot (MuJoCo's armature)."""
    base, _, plain = CASES["acrobot"]
    armatures = (0.07, 0.03)
    reference = dataclasses.replace(plain, armatures=armatures)
    joints = [cldyn.HingeAngle(child=(None, 0)), cldyn.HingeAngle(child=(0, 1), parent=(None, 0))]
    system = cldyn.ConstrainedLagrangian(
        mass=base.mass,
        potential=base.potential,
        constraint=base.constraint,
        input_matrix=base.input_matrix,
        armature=cldyn.JointArmature(joints, jnp.array(armatures)),
    )
    q, qd, u = _random_joint_states(jax.random.key(8), 2, system.num_inputs)

    @jax.jit
    @jax.vmap
    def compare(q, qd, u):
        qdd = euler_lagrange_acceleration(reference, q, qd, u)
        x, xd, xdd_ref = keypoint_state(reference, q, qd, qdd)
        rotor = 0.5 * jnp.sum(jnp.array(armatures) * qd**2)
        return system.acceleration(x, xd, u), xdd_ref, system.armature.kinetic_energy(x, xd), rotor

    xdd, xdd_ref, rotor, rotor_ref = compare(q, qd, u)
    assert np.allclose(rotor, rotor_ref, rtol=ACCEL_RTOL)
    scale = jnp.max(jnp.abs(xdd_ref), axis=1, keepdims=True)
    assert float(jnp.max(jnp.abs(xdd - xdd_ref) / scale)) < ACCEL_RTOL


def test_energy_is_conserved_without_inputs():
    system, joints, _ = CASES["chain3"]
    x, xd = joints.to_keypoints(jnp.array([0.3, -0.4, 1.0]), jnp.array([0.5, 0.1, -0.7]))
    xdd = system.acceleration(x, xd, jnp.zeros(system.num_inputs))
    assert abs(float(jax.jvp(system.energy, (x, xd), (xd, xdd))[1])) < EXACT_ATOL


def test_redundant_constraint_gives_the_non_redundant_acceleration():
    base, joints = cldyn.systems.acrobot()
    twice = eqx.tree_at(
        lambda s: s.constraint,
        base,
        cldyn.Stack([*base.constraint.constraints, cldyn.Distance(0, 1)]),
    )
    q, qd, u = _random_joint_states(jax.random.key(4), 2, 1, n=20)
    x, xd = jax.jit(jax.vmap(joints.to_keypoints))(q, qd)

    @eqx.filter_jit
    def evaluate(system):
        functions = (system.acceleration, system.multipliers, system.constraint_force)
        return [jax.vmap(f)(x, xd, u) for f in functions]

    (a_base, lam_base, f_base), (a_twice, lam_twice, f_twice) = evaluate(base), evaluate(twice)
    assert bool(jnp.all(jnp.isfinite(a_twice)))
    assert np.allclose(a_twice, a_base, rtol=REDUNDANT_RTOL, atol=REDUNDANT_ATOL)
    # least-squares multipliers share the duplicated constraint's load equally
    assert bool(jnp.all(jnp.isfinite(lam_twice)))
    assert np.allclose(lam_twice[:, 1], lam_twice[:, 2], rtol=SHARE_RTOL, atol=SHARE_ATOL)
    assert np.allclose(lam_twice[:, 1] + lam_twice[:, 2], lam_base[:, 1], rtol=SHARE_RTOL, atol=SHARE_ATOL)
    assert np.allclose(f_twice, f_base, rtol=SHARE_RTOL, atol=SHARE_ATOL)


def test_multipliers_are_the_rod_tension():
    # A point mass m on a massless rod of length L hanging at rest at angle theta, with
    # angular velocity w: the rod pulls with m (g cos(theta) + L w^2) towards the pivot.
    m, length, theta, w, g = 1.7, 0.9, 0.4, 1.3, 9.81
    system, joints = cldyn.systems.pendulum(mass=m, length=length, gravity=g, actuated=False)
    x, xd = joints.to_keypoints(jnp.array([theta]), jnp.array([w]))
    lam = system.multipliers(x, xd)
    assert np.isclose(float(lam[0]), -m * (g * np.cos(theta) + length * w**2), rtol=EXACT_RTOL)


def _four_bar_states(n, rng, ground=2.0, crank=0.5, coupler=2.0, rocker=1.5):
    """Assembled four-bar states by circle intersection, with velocities tangent to the loop."""
    phi = rng.uniform(-np.pi, np.pi, n)
    b = crank * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    d = np.array([ground, 0.0])
    dist = np.linalg.norm(d - b, axis=1, keepdims=True)
    a = (coupler**2 - rocker**2 + dist**2) / (2 * dist)
    h = np.sqrt(coupler**2 - a**2)
    e = (d - b) / dist
    c = b + a * e + h * np.stack([-e[:, 1], e[:, 0]], axis=1)
    # the tangent direction: crank rate omega moves B by omega * perp(B); C follows from
    # d/dt |C - B|^2 = 0 and d/dt |C - D|^2 = 0, a 2x2 linear system
    omega = rng.normal(size=n) * 3.0
    bd = omega[:, None] * np.stack([-b[:, 1], b[:, 0]], axis=1)
    rows = np.stack([c - b, c - d], axis=1)
    rhs = np.stack([np.sum((c - b) * bd, axis=1), np.zeros(n)], axis=1)
    cd = np.linalg.solve(rows, rhs[..., None])[..., 0]
    return np.concatenate([b, c], axis=1), np.concatenate([bd, cd], axis=1)


def test_four_bar_loop_stays_closed_to_second_order():
    system, joints = cldyn.systems.four_bar()
    assert joints is None
    rng = np.random.default_rng(0)
    x, xd = map(jnp.asarray, _four_bar_states(200, rng))
    u = jnp.asarray(rng.normal(size=(200, 1)))

    @jax.jit
    @jax.vmap
    def residuals(x, xd, u):
        xdd = system.acceleration(x, xd, u)
        hess = jax.hessian(system.constraint)(x)
        second = system.constraint.jacobian(x) @ xdd + jnp.einsum("nij,i,j->n", hess, xd, xd)
        return second, system.constraint.velocity(x, xd), system.constraint(x)

    second, first, phi = residuals(x, xd, u)
    assert float(jnp.max(jnp.abs(first))) < EXACT_ATOL  # the states are consistent
    assert np.allclose(phi, [0.5, 2.0, 1.5], rtol=EXACT_RTOL)
    assert float(jnp.max(jnp.abs(second))) < CONSTRAINT_TOL


def test_vmap_equals_loop():
    system, joints, _ = CASES["acrobot"]
    q, qd, u = _random_joint_states(jax.random.key(5), 2, 2, n=1000)
    x, xd = jax.jit(jax.vmap(joints.to_keypoints))(q, qd)
    batched = eqx.filter_jit(lambda x, xd, u: jax.vmap(system.acceleration)(x, xd, u))(x, xd, u)
    single = eqx.filter_jit(system.acceleration)
    looped = np.stack([np.asarray(single(x[i], xd[i], u[i])) for i in range(1000)])
    assert np.allclose(batched, looped, rtol=EXACT_RTOL, atol=EXACT_ATOL)


def test_jit_traces_once_per_shape():
    traces = []

    @eqx.filter_jit
    def accelerations(system, x, xd, u):
        traces.append(x.shape)
        return jax.vmap(system.acceleration)(x, xd, u)

    system, joints, _ = CASES["acrobot"]
    for seed in range(4):
        q, qd, u = _random_joint_states(jax.random.key(seed), 2, 2, n=8)
        x, xd = jax.jit(jax.vmap(joints.to_keypoints))(q, qd)
        accelerations(system, x, xd, u)
    assert traces == [(8, 4)]
    q, qd, u = _random_joint_states(jax.random.key(9), 2, 2, n=16)
    x, xd = jax.jit(jax.vmap(joints.to_keypoints))(q, qd)
    accelerations(system, x, xd, u)
    accelerations(system, x + 1e-3, xd, u)
    assert traces == [(8, 4), (16, 4)]


def test_gradients_of_every_learnable_parameter_are_finite():
    key = jax.random.key(6)
    k1, k2, k3 = jax.random.split(key, 3)
    _, joints = cldyn.systems.acrobot()
    learned = cldyn.ConstrainedLagrangian(
        mass=cldyn.PointMasses(jnp.array([1.0, 0.7])),
        potential=cldyn.MLPPotential(4, key=k1) + cldyn.Gravity.from_masses(jnp.ones(2)),
        constraint=cldyn.Stack([cldyn.Anchor(0), cldyn.Distance(0, 1)]),
        input_matrix=cldyn.MLPInput(4, 2, key=k2),
        dissipation=cldyn.JointDamping([cldyn.HingeAngle(child=(None, 0))], 0.1),
    )
    analytic, _, _ = CASES["chain3"]
    q, qd, u = _random_joint_states(k3, 2, 2, n=16)
    x, xd = jax.vmap(joints.to_keypoints)(q, qd)

    for system, (xs, xds, us) in (
        (learned, (x, xd, u)),
        (analytic, _chain3_states()),
    ):

        @eqx.filter_jit
        @eqx.filter_grad
        def grad(system):
            acc = jax.vmap(system.acceleration)(xs, xds, us)
            return jnp.mean(acc**2)

        grads = grad(system)
        leaves = jax.tree_util.tree_leaves(eqx.filter(grads, eqx.is_inexact_array))
        params = jax.tree_util.tree_leaves(eqx.filter(system, eqx.is_inexact_array))
        assert len(leaves) == len(params) > 0
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
        assert any(float(jnp.max(jnp.abs(g))) > 0 for g in leaves)


def _chain3_states():
    system, joints, _ = CASES["chain3"]
    q, qd, u = _random_joint_states(jax.random.key(7), 3, system.num_inputs, n=16)
    x, xd = jax.vmap(joints.to_keypoints)(q, qd)
    return x, xd, u


@pytest.mark.parametrize(
    "args, message",
    [
        ((jnp.zeros(3), jnp.zeros(4), jnp.zeros(1)), r"x must have shape \(4,\), got \(3,\)"),
        ((jnp.zeros(4), jnp.zeros((4, 1)), jnp.zeros(1)), r"xd must have shape \(4,\)"),
        ((jnp.zeros(4), jnp.zeros(4), jnp.zeros(2)), r"u must have shape \(1,\), got \(2,\)"),
    ],
)
def test_wrong_shapes_name_the_argument(args, message):
    system, _ = cldyn.systems.acrobot()
    with pytest.raises(ValueError, match=message):
        system.acceleration(*args)
    with pytest.raises(ValueError, match=message):
        eqx.filter_jit(system.acceleration)(*args)


def test_missing_control_means_zero():
    system, joints = cldyn.systems.acrobot()
    x, xd = joints.to_keypoints(jnp.array([0.2, 0.3]), jnp.array([0.1, 0.0]))
    assert np.allclose(system.acceleration(x, xd), system.acceleration(x, xd, jnp.zeros(1)))


def test_components_are_type_checked():
    with pytest.raises(TypeError, match="potential"):
        cldyn.ConstrainedLagrangian(mass=cldyn.PointMasses(jnp.ones(1)), potential=lambda x: x)


def test_unconstrained_system_is_newton():
    masses = jnp.array([2.0, 0.5])
    system = cldyn.ConstrainedLagrangian(
        mass=cldyn.PointMasses(masses), potential=cldyn.Gravity.from_masses(masses, g=9.81)
    )
    xdd = system.acceleration(jnp.zeros(4), jnp.ones(4))
    assert np.allclose(xdd, [0, -9.81, 0, -9.81], rtol=NEWTON_RTOL)
    assert system.multipliers(jnp.zeros(4), jnp.ones(4)).shape == (0,)


def test_a_float32_model_stays_in_float32():
    """Every component computes in its own dtype: no float64 constant leaks into float32 training
    (the tests run with strict dtype promotion, so a leak raises)."""
    base, joints, _ = CASES["acrobot"]
    coords = [cldyn.HingeAngle(child=(None, 0)), cldyn.HingeAngle(child=(0, 1), parent=(None, 0))]
    drag = cldyn.KeypointDrag(jnp.full(2, 0.1), jnp.full(2, 0.01))
    springs = cldyn.JointSpring(coords[1], stiffness=0.5) + cldyn.Spring(0, 1, stiffness=1.0)
    models = [
        cldyn.ConstrainedLagrangian(
            mass=base.mass,
            potential=base.potential + springs,
            constraint=base.constraint,
            input_matrix=base.input_matrix,
            dissipation=cldyn.JointDamping(coords, 0.1) + cldyn.JointCoulomb(coords, 0.05) + drag,
            armature=cldyn.JointArmature(coords, 0.05),
        ),
        cldyn.ConstrainedLagrangian(
            mass=cldyn.CoupledMasses(jnp.ones(2)),
            potential=cldyn.MLPPotential(4, key=jax.random.key(0)),
            constraint=base.constraint,
            input_matrix=cldyn.MLPInput(4, 2, key=jax.random.key(1)),
        ),
    ]
    single = lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a
    x, xd = jax.tree.map(single, joints.to_keypoints(jnp.array([0.3, 0.4]), jnp.array([0.1, -0.2])))
    u = jnp.ones(2, jnp.float32)

    @eqx.filter_jit
    def outputs(model):
        model = jax.tree.map(single, model)
        return (
            model.acceleration(x, xd, u),
            model.multipliers(x, xd, u),
            model.constraint_force(x, xd, u),
            model.inverse_dynamics(x, xd, xd, u),
            model.energy(x, xd),
            model.power(x, xd, u),
            model.mass.inverse(),
        )

    for model in models:
        dtypes = [o.dtype for o in outputs(model)]
        assert dtypes == [jnp.float32] * len(dtypes)
