"""Constraints, masses, coordinates and potentials, each against an independent fact."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn

CURVATURE_TOL = 1e-12


def _rot(theta):
    return np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])


def test_rigid_body_block_gives_the_rigid_body_kinetic_energy():
    # a body with its centre of mass off the line between its two keypoints, in random rigid motions:
    # the block's 1/2 xd^T M xd equals 1/2 m |v_com|^2 + 1/2 I omega^2
    rng = np.random.default_rng(0)
    for _ in range(200):
        mass, inertia = rng.uniform(0.1, 3.0), rng.uniform(0.01, 1.0)
        body = rng.normal(size=(2, 2))  # the two keypoints, in the body frame
        com = rng.normal(size=2) * 0.7  # anywhere, generally off the segment
        block = np.asarray(cldyn.rigid_body_mass(mass, inertia, com, body))
        theta, omega = rng.uniform(-np.pi, np.pi), rng.normal()
        position, velocity = rng.normal(size=2), rng.normal(size=2)  # of the centre of mass
        rot = _rot(theta)
        # world velocities of the keypoints: v + omega x (p - c)
        rel = (rot @ (body - com).T).T
        xd = np.concatenate([velocity + omega * np.array([-r[1], r[0]]) for r in rel])
        expected = 0.5 * mass * velocity @ velocity + 0.5 * inertia * omega**2
        assert np.isclose(0.5 * xd @ block @ xd, expected, rtol=1e-12)
        del position


def test_pivot_body_block_and_gravity_weights():
    rng = np.random.default_rng(1)
    for _ in range(100):
        mass, inertia = rng.uniform(0.1, 3.0), rng.uniform(0.01, 1.0)
        pivot, point, com = rng.normal(size=(3, 2))
        block = np.asarray(cldyn.pivot_body_mass(mass, inertia, com, pivot, point))
        weights = np.asarray(cldyn.pivot_body_gravity(mass, com, pivot, point))
        theta, omega = rng.uniform(-np.pi, np.pi), rng.normal()
        rot = _rot(theta)
        p = pivot + rot @ (point - pivot)
        c = pivot + rot @ (com - pivot)
        perp = lambda r: np.array([-r[1], r[0]])
        pd, cd = omega * perp(p - pivot), omega * perp(c - pivot)
        expected = 0.5 * mass * cd @ cd + 0.5 * inertia * omega**2
        assert np.isclose(0.5 * pd @ block @ pd, expected, rtol=1e-12)
        # the gravity weights give m g c_y up to a constant: compare two orientations
        rot2 = _rot(theta + 0.7)
        p2, c2 = pivot + rot2 @ (point - pivot), pivot + rot2 @ (com - pivot)
        assert np.isclose(weights @ (p2 - p), mass * (c2[1] - c[1]), rtol=1e-10, atol=1e-12)


def test_masses_reject_invalid_values_with_clear_messages():
    with pytest.raises(ValueError, match="keypoint masses must be positive"):
        cldyn.PointMasses(jnp.array([1.0, -0.5]))
    with pytest.raises(ValueError, match="must be positive definite; its smallest eigenvalue"):
        cldyn.ConstantMass(jnp.diag(jnp.array([1.0, 0.0])))
    with pytest.raises(ValueError, match="must be symmetric"):
        cldyn.ConstantMass(jnp.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match=r"block for keypoints \(0, 1\) must have shape \(4, 4\)"):
        cldyn.ConstantMass.from_blocks([((0, 1), jnp.eye(2))], 2)


def test_constant_mass_parameterisation_round_trips():
    a = np.random.default_rng(2).normal(size=(4, 4))
    matrix = a @ a.T + 4 * np.eye(4)
    mass = cldyn.ConstantMass(matrix)
    assert np.allclose(mass.matrix(), matrix, rtol=1e-12)
    v = jnp.arange(4.0)
    assert np.allclose(mass.solve(mass.matvec(v)), v, rtol=1e-12)
    assert np.allclose(mass.inverse() @ matrix, np.eye(4), atol=1e-12)


@pytest.mark.parametrize(
    "constraint",
    [
        cldyn.Distance(0, 1),
        cldyn.Anchor(1, jnp.array([0.3, -0.2])),
        cldyn.FixedCoordinate(0, axis=1),
        cldyn.Stack([cldyn.Anchor(0), cldyn.Distance(0, 1), cldyn.FixedCoordinate(1, 0)]),
        cldyn.FromFunction(lambda x: jnp.stack([x[0] * x[3] - x[1] ** 2, jnp.sin(x[2])]), num_constraints=2),
    ],
    ids=["distance", "anchor", "fixed", "stack", "function"],
)
def test_jacobian_and_curvature_match_autodiff_of_phi(constraint):
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, xd = jnp.asarray(rng.normal(size=4)), jnp.asarray(rng.normal(size=4))
        jac = jax.jacfwd(constraint)(x)
        hess = jax.hessian(constraint)(x)
        assert np.allclose(constraint.jacobian(x), jac, atol=CURVATURE_TOL)
        assert np.allclose(
            constraint.curvature(x, xd), jnp.einsum("nij,i,j->n", hess, xd, xd), atol=CURVATURE_TOL
        )
        assert np.allclose(constraint.velocity(x, xd), jac @ xd, atol=CURVATURE_TOL)


def test_constraint_arguments_are_checked():
    with pytest.raises(ValueError, match="two different keypoints"):
        cldyn.Distance(1, 1)
    with pytest.raises(ValueError, match=r"axis must be in \[0, 2\)"):
        cldyn.FixedCoordinate(0, axis=2)
    with pytest.raises(ValueError, match=r"Anchor point must have shape \(2,\)"):
        cldyn.Anchor(0, jnp.zeros(3))
    bad = cldyn.FromFunction(lambda x: x[:3], num_constraints=2)
    with pytest.raises(ValueError, match=r"returned shape \(3,\), but num_constraints=2"):
        bad(jnp.zeros(4))


def test_hinge_angle_and_slider_position():
    # a link at absolute angle a from straight down, and a second one at relative angle b
    a, b = 0.7, -1.9
    p1 = np.array([np.sin(a), -np.cos(a)])
    p2 = p1 + 0.5 * np.array([np.sin(a + b), -np.cos(a + b)])
    x = jnp.asarray(np.concatenate([p1, p2]))
    shoulder = cldyn.HingeAngle(child=(None, 0))
    elbow = cldyn.HingeAngle(child=(0, 1), parent=(None, 0))
    assert np.isclose(shoulder(x), a) and np.isclose(elbow(x), b)
    assert np.isclose(cldyn.HingeAngle(child=(None, 0), sign=-1.0, offset=0.2)(x), -a - 0.2)
    # grad q is perpendicular to the link, of length 1 / L: a torque tau gives a force tau / L
    g = shoulder.gradient(x)
    assert np.isclose(np.linalg.norm(g[:2]), 1.0) and np.isclose(g[:2] @ p1, 0.0, atol=1e-15)
    slider = cldyn.SliderPosition(1, axis=(2.0, 0.0), origin=(0.5, 0.0), offset=0.1)
    assert np.isclose(slider(x), p2[0] - 0.5 - 0.1)
    assert np.isclose(cldyn.wrap_angle(3 * np.pi / 2), -np.pi / 2)


def test_potentials_and_their_sum():
    x = jnp.array([0.3, -0.4, 1.0, 0.5])
    gravity = cldyn.Gravity.from_masses(jnp.array([2.0, 0.5]), g=9.81)
    spring = cldyn.Spring(0, 1, stiffness=3.0, rest_length=1.0)
    anchored = cldyn.Spring(0, None, stiffness=2.0, point=(0.0, 0.0))
    total = gravity + spring + anchored
    assert isinstance(total, cldyn.Sum) and len(total.terms) == 3
    length = np.hypot(0.7, 0.9)
    expected = 9.81 * (2.0 * -0.4 + 0.5 * 0.5) + 1.5 * (length - 1.0) ** 2 + 1.0 * 0.25
    assert np.isclose(total(x), expected, rtol=1e-12)
    assert np.allclose(total.gradient(x), jax.grad(lambda y: total(y))(x))
    mlp = cldyn.MLPPotential(4, key=jax.random.key(0))
    assert mlp(x).shape == () and abs(float(mlp(x))) < 1.0  # small initial weights (appendix A.4)
    g = cldyn.MLPInput(4, 2, key=jax.random.key(1))(x)
    assert g.shape == (4, 2)


def test_joint_map_round_trip():
    system, joints = cldyn.systems.chain(3, lengths=[1.0, 0.5, 0.8])
    q, qd = jnp.array([0.3, -2.0, 1.0]), jnp.array([0.5, 0.1, -0.7])
    x, xd = joints.to_keypoints(q, qd)
    q2, qd2 = joints.to_joints(x, xd)
    assert np.allclose(q2, q, atol=1e-12) and np.allclose(qd2, qd, atol=1e-12)
    assert np.allclose(system.constraint(x), [1.0, 0.5, 0.8], atol=1e-12)
