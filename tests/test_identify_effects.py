"""The effect library and the dissipative terms it adds, against closed forms.

Each dissipative term is checked on known states against the force written by hand; the quadratic
joint damping also against the reference chain's own kinematics (its generalised force is
`-c |qd| qd` on its joint and nothing on the others). Each effect of `cldyn.EFFECTS` is checked for
agreement between its two halves: the candidate's force per unit parameter (what the regression
sees) and the change of the model's inverse dynamics when the effect is added as a cldyn term.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import keypoint_state, reference_systems

import cldyn
from cldyn._identify.base import Context, Point
from cldyn._identify.result import Detection

FORCE_ATOL = 1e-12
GENERALISED_ATOL = 1e-10


def _pendulum_state(theta, omega, length):
    x = length * jnp.array([jnp.sin(theta), -jnp.cos(theta)])
    return x, length * omega * jnp.array([jnp.cos(theta), jnp.sin(theta)])


@pytest.mark.parametrize("theta, omega", [(0.3, 2.0), (-2.0, -1.5), (3.0, 0.0)])
def test_joint_dissipations_on_a_pendulum_match_the_hand_formulae(theta, omega):
    length = 0.7
    x, xd = _pendulum_state(theta, omega, length)
    # grad q = (cos, sin) / L for the angle from straight down of the point L (sin, -cos)
    direction = jnp.array([np.cos(theta), np.sin(theta)]) / length
    hinge = [cldyn.HingeAngle(child=(None, 0))]
    b, c, f, vs = 0.3, 0.05, 0.2, 0.1
    cases = [
        (cldyn.JointDamping(hinge, b), -b * omega),
        (cldyn.JointQuadraticDamping(hinge, c), -c * abs(omega) * omega),
        (cldyn.JointCoulomb(hinge, f, velocity_scale=vs), -f * np.tanh(omega / vs)),
    ]
    for term, torque in cases:
        assert np.allclose(term(x, xd), torque * direction, atol=FORCE_ATOL), type(term).__name__
        assert float(term.power(x, xd)) <= 0.0


def test_keypoint_drag_matches_the_hand_formula():
    drag = cldyn.KeypointDrag(jnp.array([0.4, 0.0]), jnp.array([0.0, 0.3]))
    x = jnp.zeros(4)
    xd = jnp.array([1.0, -2.0, 3.0, 4.0])
    expected = np.array([-0.4 * 1.0, -0.4 * -2.0, -0.3 * 5.0 * 3.0, -0.3 * 5.0 * 4.0])
    assert np.allclose(drag(x, xd), expected, atol=FORCE_ATOL)


def test_quadratic_joint_damping_is_a_torque_on_its_joint_alone():
    # through the reference's own kinematics x = F(q): the generalised force J^T F of the Cartesian
    # force is -c |qd_j| qd_j on the damped joint and zero on the others
    system, joints, reference = reference_systems()["chain3"]
    elbow = cldyn.HingeAngle(child=(0, 1), parent=(None, 0))
    c = 0.07
    term = cldyn.JointQuadraticDamping([elbow], c)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q, qd = rng.uniform(-2, 2, size=3), rng.uniform(-3, 3, size=3)
        x, xd = keypoint_state(reference, jnp.asarray(q), jnp.asarray(qd))
        jacobian = jax.jacfwd(reference.keypoints)(jnp.asarray(q))
        generalised = jacobian.T @ term(x, xd)
        assert np.allclose(generalised, [0.0, -c * abs(qd[1]) * qd[1], 0.0], atol=GENERALISED_ATOL)


def _context(name):
    system, joints, reference = reference_systems()[name]
    n = reference.n
    coordinates = [cldyn.HingeAngle(child=(None, 0))]
    coordinates += [
        cldyn.HingeAngle(child=(i - 1, i), parent=(None if i == 1 else i - 2, i - 1)) for i in range(1, n)
    ]
    context = Context(
        system,
        tuple(coordinates),
        tuple(f"joint{j}" for j in range(n)),
        tuple(f"u{a}" for a in range(system.num_inputs)),
        tuple(f"keypoint{i}" for i in range(n)),
    )
    return system, reference, context


@pytest.mark.parametrize("effect", cldyn.EFFECTS, ids=lambda e: e.name)
def test_every_effect_adds_the_force_its_features_describe(effect):
    # adding an effect with coefficients theta changes M xdd - f by -(force per unit parameter) @ theta
    system, reference, context = _context("acrobot")
    rng = np.random.default_rng(1)
    candidates = effect.candidates(context)
    assert candidates, effect.name
    for candidate in candidates:
        theta = rng.uniform(0.2, 0.5, size=len(candidate.columns))
        augmented = cldyn.augment(system, [_detection(candidate, theta)], context)
        # states within (-pi/2, pi/2) keep the spring's wrapped angle equal to the unwrapped one
        q, qd, qdd = rng.uniform(-1.5, 1.5, size=(3, 2))
        x, xd, xdd = keypoint_state(reference, jnp.asarray(q), jnp.asarray(qd), jnp.asarray(qdd))
        u = jnp.asarray(rng.uniform(-1, 1, size=system.num_inputs))
        point = Point(x, xd, xdd, u, jnp.asarray(q))
        expected = -effect.force(candidate, context, point) @ jnp.asarray(theta)
        change = augmented.inverse_dynamics(x, xd, xdd, u) - system.inverse_dynamics(x, xd, xdd, u)
        assert np.allclose(change, expected, atol=1e-10), candidate.label
        # and the refitted reading gives the coefficients back in the effect's own meaning
        read = effect.refitted(augmented, candidate, context)
        if read is not None:
            assert np.isclose(read["value"], candidate.parameters(theta)["value"]), candidate.label
        # where the term follows the effect, the model changes as the features say: the wrapped angle
        # equals the unwrapped one within half a turn of a spring's rest, so no sample is flagged
        outside = effect.unrepresentable(candidate, candidate.parameters(theta), np.asarray(q)[None])
        assert outside is None or not outside.any(), candidate.label


def test_a_hinge_spring_wound_past_half_a_turn_is_flagged():
    # keypoints give an angle modulo a turn: a spring about rest 0.3 wound to 0.3 + 4 rad (MuJoCo counts
    # turns) pulls the other way in the keypoint model, whose wrapped angle is 0.3 + 4 - 2 pi
    system, reference, context = _context("acrobot")
    candidate = cldyn.JointSpringEffect().candidates(context)[0]
    q = np.array([[[0.3 + 4.0, 0.0], [0.3 - 3.0, 0.0], [0.3 + 3.0, 0.0], [0.3 - 4.0, 1.0]]])
    outside = candidate.effect.unrepresentable(candidate, {"springref": 0.3}, q)
    np.testing.assert_array_equal(outside, [[True, False, False, True]])


def _detection(candidate, theta):
    parameters = candidate.parameters(theta)
    return Detection(
        candidate, parameters["value"], (0.0, 0.0), parameters, 0.0, 0.0, 0.0, 0.0, 0.0, (), 1, True, theta
    )


def test_effects_are_named_once_and_found_by_name():
    names = [e.name for e in cldyn.EFFECTS]
    assert len(set(names)) == len(names)
    assert {
        "joint_damping",
        "joint_quadratic_damping",
        "joint_coulomb",
        "joint_spring",
        "joint_armature",
        "actuator_gain",
        "keypoint_drag",
        "point_mass",
    } == set(names)
