"""Constraints, masses, coordinates and potentials, each against an independent fact."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
from cldyn._linalg import UNROLL_MAX, small_solve

CURVATURE_TOL = 1e-12
# closed forms evaluated in float64
EXACT_RTOL = 1e-12
EXACT_ATOL = 1e-12
GRAVITY_RTOL = 1e-10
ORTHOGONAL_ATOL = 1e-15


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
        assert np.isclose(0.5 * xd @ block @ xd, expected, rtol=EXACT_RTOL)
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
        assert np.isclose(0.5 * pd @ block @ pd, expected, rtol=EXACT_RTOL)
        # the gravity weights give m g c_y up to a constant: compare two orientations
        rot2 = _rot(theta + 0.7)
        p2, c2 = pivot + rot2 @ (point - pivot), pivot + rot2 @ (com - pivot)
        assert np.isclose(weights @ (p2 - p), mass * (c2[1] - c[1]), rtol=GRAVITY_RTOL, atol=EXACT_ATOL)


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
    assert np.allclose(mass.matrix(), matrix, rtol=EXACT_RTOL)
    v = jnp.arange(4.0)
    assert np.allclose(mass.solve(mass.matvec(v)), v, rtol=EXACT_RTOL)
    assert np.allclose(mass.inverse() @ matrix, np.eye(4), atol=EXACT_ATOL)


@pytest.mark.parametrize(
    "constraint",
    [
        cldyn.Distance(0, 1),
        cldyn.Anchor(1, jnp.array([0.3, -0.2])),
        cldyn.FixedCoordinate(0, axis=1),
        cldyn.Stack([cldyn.Anchor(0), cldyn.Distance(0, 1), cldyn.FixedCoordinate(1, 0)]),
        cldyn.FromFunction(lambda x: jnp.stack([x[0] * x[3] - x[1] ** 2, jnp.sin(x[2])]), num_constraints=2),
        cldyn.Stack(
            [cldyn.LinearConstraint([[0.6, -0.8, 0.0, 0.0], [1.0, 0.0, -1.0, 0.0]]), cldyn.Distance(0, 1)]
        ),
    ],
    ids=["distance", "anchor", "fixed", "stack", "function", "linear"],
)
def test_jacobian_and_curvature_match_autodiff_of_phi(constraint):
    rng = np.random.default_rng(3)
    x, xd = jnp.asarray(rng.normal(size=(20, 4))), jnp.asarray(rng.normal(size=(20, 4)))

    @jax.jit
    @jax.vmap
    def both(x, xd):
        jac = jax.jacfwd(constraint)(x)
        curvature = jnp.einsum("nij,i,j->n", jax.hessian(constraint)(x), xd, xd)
        closed = (constraint.jacobian(x), constraint.curvature(x, xd), constraint.velocity(x, xd))
        return closed, (jac, curvature, jac @ xd)

    for closed, autodiff in zip(*both(x, xd)):
        assert np.allclose(closed, autodiff, atol=CURVATURE_TOL)


@pytest.mark.parametrize("keypoints", [3, 5])
def test_stack_of_segments_matches_its_members(keypoints):
    # Distance and Anchor rows of a Stack are evaluated together in one pass; interleaved with other
    # rows, in 3-D, with keypoints that no segment uses (k = 15: coordinates 9-11 unused)
    members = [
        cldyn.Distance(0, 1, dim=3),
        cldyn.FixedCoordinate(1, axis=2, dim=3),
        cldyn.Anchor(2, jnp.array([0.3, -0.2, 0.5]), dim=3),
        cldyn.Distance(keypoints - 1, 0, dim=3),
        cldyn.Anchor(1, dim=3),
    ]
    stack = cldyn.Stack(members)
    rng = np.random.default_rng(4)
    x, xd = jnp.asarray(rng.normal(size=3 * keypoints)), jnp.asarray(rng.normal(size=3 * keypoints))
    values = np.concatenate([np.asarray(c(x)) for c in members])
    rows = np.concatenate([np.asarray(c.jacobian(x)) for c in members])
    curvatures = np.concatenate([np.asarray(c.curvature(x, xd)) for c in members])
    assert np.allclose(stack(x), values, rtol=EXACT_RTOL)
    assert np.allclose(stack.jacobian(x), rows, rtol=EXACT_RTOL, atol=EXACT_ATOL)
    assert np.allclose(stack.curvature(x, xd), curvatures, rtol=EXACT_RTOL, atol=EXACT_ATOL)
    assert np.allclose(stack.jacobian(x), jax.jacfwd(stack)(x), atol=CURVATURE_TOL)
    hessian_term = jnp.einsum("nij,i,j->n", jax.hessian(stack)(x), xd, xd)
    assert np.allclose(stack.curvature(x, xd), hessian_term, atol=CURVATURE_TOL)


def test_constraint_arguments_are_checked():
    with pytest.raises(ValueError, match="two different keypoints"):
        cldyn.Distance(1, 1)
    with pytest.raises(ValueError, match=r"axis must be in \[0, 2\)"):
        cldyn.FixedCoordinate(0, axis=2)
    with pytest.raises(ValueError, match=r"Anchor point must have shape \(2,\)"):
        cldyn.Anchor(0, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"rows must have shape \(n, k\)"):
        cldyn.LinearConstraint([1.0, 0.0])
    with pytest.raises(ValueError, match="not all zero"):
        cldyn.LinearConstraint([[1.0, 0.0], [0.0, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        cldyn.LinearConstraint([[np.nan, 1.0]])
    with pytest.raises(ValueError, match="rows are for 2 coordinates, x has 4"):
        cldyn.LinearConstraint([[1.0, 0.0]])(jnp.zeros(4))
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
    assert np.isclose(np.linalg.norm(g[:2]), 1.0) and np.isclose(g[:2] @ p1, 0.0, atol=ORTHOGONAL_ATOL)
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
    assert np.isclose(total(x), expected, rtol=EXACT_RTOL)
    # grad V in closed form: g w, the springs' k (|d| - l0) d / |d| on both ends, and 2 x0 for the anchor
    delta = np.array([0.3 - 1.0, -0.4 - 0.5])
    pull = 3.0 * (length - 1.0) * delta / length
    closed_form = 9.81 * np.array([0.0, 2.0, 0.0, 0.5]) + np.concatenate([pull, -pull])
    closed_form[:2] += 2.0 * np.array([0.3, -0.4])
    assert np.allclose(total.gradient(x), closed_form, rtol=FORCE_RTOL, atol=FORCE_ATOL)
    mlp = cldyn.MLPPotential(4, key=jax.random.key(0))
    assert mlp(x).shape == () and abs(float(mlp(x))) < 1.0  # small initial weights (appendix A.4)
    g = cldyn.MLPInput(4, 2, key=jax.random.key(1))(x)
    assert g.shape == (4, 2)


def test_joint_map_round_trip():
    system, joints = cldyn.systems.chain(3, lengths=[1.0, 0.5, 0.8])
    q, qd = jnp.array([0.3, -2.0, 1.0]), jnp.array([0.5, 0.1, -0.7])
    x, xd = joints.to_keypoints(q, qd)
    q2, qd2 = joints.to_joints(x, xd)
    assert np.allclose(q2, q, atol=EXACT_ATOL) and np.allclose(qd2, qd, atol=EXACT_ATOL)
    assert np.allclose(system.constraint(x), [1.0, 0.5, 0.8], atol=EXACT_ATOL)


# -- joint forces and potentials against closed forms ---------------------------------------------
# The gradient of the angle of a planar vector c is perp(c) / |c|^2; an acrobot's shoulder angle is
# the angle of keypoint 0 about the origin, its elbow angle that of (x1 - x0) minus the shoulder's.

ACROBOT_JOINTS = (cldyn.HingeAngle(child=(None, 0)), cldyn.HingeAngle(child=(0, 1), parent=(None, 0)))
FORCE_RTOL = 1e-12
FORCE_ATOL = 1e-12


def _perp(v):
    return np.array([-v[1], v[0]])


def _angle_gradient(c):
    return _perp(c) / (c @ c)


def _acrobot_gradients(x):
    """`[grad q_shoulder, grad q_elbow]` as columns, shape `(4, 2)`."""
    p0, p1 = x[:2], x[2:]
    shoulder = np.concatenate([_angle_gradient(p0), np.zeros(2)])
    link = p1 - p0
    elbow = np.concatenate([-_angle_gradient(link) - _angle_gradient(p0), _angle_gradient(link)])
    return np.stack([shoulder, elbow], axis=1)


def _random_states(seed, n=20):
    rng = np.random.default_rng(seed)
    return [(rng.normal(size=4), rng.normal(size=4) * 2.0) for _ in range(n)]


@pytest.mark.parametrize("kind", ["damping", "coulomb"])
def test_joint_friction_matches_its_closed_form(kind):
    coefficients = np.array([0.3, 0.8])
    velocity_scale = 0.1
    if kind == "damping":
        term = cldyn.JointDamping(ACROBOT_JOINTS, jnp.asarray(coefficients))
        joint_force = lambda qd: -coefficients * qd
    else:
        term = cldyn.JointCoulomb(ACROBOT_JOINTS, jnp.asarray(coefficients), velocity_scale=velocity_scale)
        joint_force = lambda qd: -coefficients * np.tanh(qd / velocity_scale)
    force = jax.jit(term.__call__)
    for x, xd in _random_states(4):
        grads = _acrobot_gradients(x)
        qd = grads.T @ xd
        expected = grads @ joint_force(qd)
        assert np.allclose(force(jnp.asarray(x), jnp.asarray(xd)), expected, rtol=FORCE_RTOL, atol=FORCE_ATOL)
        assert float(term.power(jnp.asarray(x), jnp.asarray(xd))) <= 0.0


def test_coulomb_friction_tends_to_the_friction_force():
    # far above the velocity scale the joint torque is the friction torque, against the motion
    coulomb = cldyn.JointCoulomb(ACROBOT_JOINTS[:1], 0.4, velocity_scale=1e-3)
    p = np.array([np.sin(0.3), -np.cos(0.3)])  # |p| = 1, so grad q = perp(p) and qd = xd . perp(p)
    x = jnp.asarray(np.concatenate([p, [0.0, -2.0]]))
    for rate in (-2.0, 0.5):
        xd = jnp.asarray(np.concatenate([rate * _perp(p), [0.0, 0.0]]))
        torque = float(jnp.dot(coulomb(x, xd)[:2], _perp(p)))
        assert np.isclose(torque, -0.4 * np.sign(rate), rtol=FORCE_RTOL)
    with pytest.raises(ValueError, match="velocity_scale must be positive"):
        cldyn.JointCoulomb(ACROBOT_JOINTS, 0.1, velocity_scale=0.0)


def test_keypoint_drag_matches_its_closed_form():
    linear, quadratic = np.array([0.2, 0.5]), np.array([0.1, 0.3])
    drag = cldyn.KeypointDrag(jnp.asarray(linear), jnp.asarray(quadratic))
    for x, xd in _random_states(5):
        v = xd.reshape(2, 2)
        speed = np.linalg.norm(v, axis=1)
        expected = -((linear + quadratic * speed)[:, None] * v).reshape(-1)
        assert np.allclose(drag(jnp.asarray(x), jnp.asarray(xd)), expected, rtol=FORCE_RTOL, atol=FORCE_ATOL)
        power = -np.sum(linear * speed**2 + quadratic * speed**3)
        assert np.isclose(drag.power(jnp.asarray(x), jnp.asarray(xd)), power, rtol=FORCE_RTOL)
    # at rest: no force, and a finite derivative (the speed's square root is guarded)
    rest = jnp.zeros(4)
    assert np.array_equal(drag(rest, rest), np.zeros(4))
    jacobian = jax.jacfwd(drag, argnums=1)(rest, rest)
    assert np.allclose(jacobian, -np.diag(np.repeat(linear, 2)), atol=FORCE_ATOL)
    # the shape annotation (under the tests' jaxtyping hook) or the check in __check_init__ refuses it
    with pytest.raises((TypeError, ValueError)):
        cldyn.KeypointDrag(jnp.ones(2), jnp.ones(3))


def test_joint_spring_on_a_hinge_matches_its_closed_form():
    stiffness, rest = 1.7, -3.0
    spring = cldyn.JointSpring(ACROBOT_JOINTS[0], stiffness=stiffness, rest=rest)
    for angle in (0.4, 3.0, -2.5):  # 3.0 - (-3.0) wraps to 6.0 - 2 pi
        p = 0.8 * np.array([np.sin(angle), -np.cos(angle)])
        x = jnp.asarray(np.concatenate([p, [0.3, -1.0]]))
        delta = (angle - rest + np.pi) % (2 * np.pi) - np.pi
        assert np.isclose(spring(x), 0.5 * stiffness * delta**2, rtol=FORCE_RTOL)
        expected = np.concatenate([stiffness * delta * _angle_gradient(p), np.zeros(2)])
        assert np.allclose(spring.gradient(x), expected, rtol=FORCE_RTOL, atol=FORCE_ATOL)


def test_joint_spring_on_a_slider_matches_its_closed_form():
    stiffness, rest = 2.0, 0.3
    slider = cldyn.SliderPosition(1, axis=(3.0, 4.0), origin=(0.5, -0.2))
    spring = cldyn.JointSpring(slider, stiffness=stiffness, rest=rest, periodic=False)
    rng = np.random.default_rng(6)
    for _ in range(10):
        x = rng.normal(size=4) * 3.0
        stretch = 0.6 * (x[2] - 0.5) + 0.8 * (x[3] + 0.2) - rest  # never wrapped
        assert np.isclose(spring(jnp.asarray(x)), 0.5 * stiffness * stretch**2, rtol=FORCE_RTOL)
        expected = np.array([0.0, 0.0, 0.6, 0.8]) * stiffness * stretch
        assert np.allclose(spring.gradient(jnp.asarray(x)), expected, rtol=FORCE_RTOL, atol=FORCE_ATOL)


def test_armature_energy_and_velocity_product_force_match_their_closed_forms():
    # one hinge about the origin: q = angle of c = x0, so xd^T D2q xd = -2 (xd . perp(c)) (c . xd) / |c|^4
    armature = cldyn.JointArmature(ACROBOT_JOINTS[:1], 0.05)
    for x, xd in _random_states(7):
        c, v = x[:2], xd[:2]
        grad = np.concatenate([_angle_gradient(c), np.zeros(2)])
        rate = grad @ xd
        curvature = -2 * (v @ _perp(c)) * (c @ v) / (c @ c) ** 2
        x_, xd_ = jnp.asarray(x), jnp.asarray(xd)
        assert np.isclose(armature.kinetic_energy(x_, xd_), 0.5 * 0.05 * rate**2, rtol=FORCE_RTOL)
        assert np.allclose(
            armature.bias(x_, xd_), -0.05 * grad * curvature, rtol=FORCE_RTOL, atol=FORCE_ATOL
        )


# -- numerics: central differences (eq. 11, 12) and the small dense solve ---------------------------

DIFFERENCE_ATOL = 1e-11
ORDER_TOL = 0.05
SOLVE_RTOL = 1e-10
# lineax's SVD against numpy's pseudo-inverse on a singular system
LSTSQ_TOL = 1e-8


def test_central_difference_is_exact_on_quadratics_and_second_order():
    dt = 0.01
    t = dt * np.arange(50)
    coefficients = np.random.default_rng(8).normal(size=(3, 2, 4))  # (c0, c1, c2) for (runs=2, k=4)
    x = sum(c[:, None, :] * t[None, :, None] ** p for p, c in enumerate(coefficients))
    derivative = coefficients[1][:, None, :] + 2 * coefficients[2][:, None, :] * t[None, 1:-1, None]
    out = cldyn.central_difference(jnp.asarray(x), dt)
    assert out.shape == (2, 48, 4)
    assert np.allclose(out, derivative, atol=DIFFERENCE_ATOL)
    # on sin the error is h^2 / 6 |x'''|: the slope of log error against log h is 2
    errors = []
    steps = (0.1, 0.05, 0.025)
    for h in steps:
        ts = h * np.arange(int(round(2.0 / h)) + 1)
        estimate = cldyn.central_difference(jnp.asarray(np.sin(ts))[:, None], h)[:, 0]
        errors.append(float(np.max(np.abs(estimate - np.cos(ts[1:-1])))))
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - 2.0) < ORDER_TOL, slope


def _well_conditioned(rng, n, symmetric):
    if symmetric:
        basis = np.linalg.qr(rng.normal(size=(n, n)))[0]
        return basis @ np.diag(rng.uniform(1.0, 10.0, n)) @ basis.T
    # diagonally dominant: LU without pivoting is stable
    a = rng.normal(size=(n, n))
    return a + np.diag(np.sum(np.abs(a), axis=1) + 1.0)


# sizes of the unrolled factorisation (a constraint count) and one past it, where lineax takes over
@pytest.mark.parametrize("n", [1, 2, 3, 6, UNROLL_MAX + 2])
def test_small_solve_matches_numpy_on_well_conditioned_systems(n):
    rng = np.random.default_rng(n)
    solve = jax.jit(jax.vmap(small_solve))
    for symmetric in (True, False):
        matrices = np.stack([_well_conditioned(rng, n, symmetric) for _ in range(8)])
        vectors, blocks = rng.normal(size=(8, n)), rng.normal(size=(8, n, 3))
        assert np.allclose(solve(matrices, vectors), np.linalg.solve(matrices, vectors[..., None])[..., 0],
                           rtol=SOLVE_RTOL, atol=SOLVE_RTOL)
        assert np.allclose(solve(matrices, blocks), np.linalg.solve(matrices, blocks), rtol=SOLVE_RTOL,
                           atol=SOLVE_RTOL)


def test_small_solve_on_singular_systems_is_exact_when_consistent_and_always_finite():
    # the same constraint twice: rows 0 and 2 of B agree, so A = B B^T has a zero pivot at 2
    rng = np.random.default_rng(9)
    b = rng.normal(size=(3, 3))
    b[2] = b[0]
    matrix = b @ b.T
    consistent = matrix @ rng.normal(size=3)
    z = np.asarray(small_solve(jnp.asarray(matrix), jnp.asarray(consistent)))
    assert np.allclose(matrix @ z, consistent, rtol=SOLVE_RTOL, atol=SOLVE_RTOL)
    assert z[2] == 0.0  # the redundant row gets a zero component
    inconsistent = np.asarray(small_solve(jnp.asarray(matrix), jnp.asarray(rng.normal(size=3))))
    assert np.all(np.isfinite(inconsistent))
    # above the unrolled size: lineax's least-squares solution of least norm
    n = UNROLL_MAX + 2
    b = rng.normal(size=(n, n))
    b[-1] = b[0]
    matrix, rhs = b @ b.T, rng.normal(size=n)
    z = np.asarray(small_solve(jnp.asarray(matrix), jnp.asarray(rhs)))
    assert np.allclose(z, np.linalg.pinv(matrix) @ rhs, rtol=LSTSQ_TOL, atol=LSTSQ_TOL)
