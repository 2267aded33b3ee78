"""Energy shaping (eq. 32) on analytic systems."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn

SUCCESS_RADIUS = 0.05  # metres, on every keypoint


def _upright(name):
    if name == "pendulum":
        return cldyn.systems.pendulum(), jnp.array([np.pi])
    if name == "cartpole":
        return cldyn.systems.cartpole(actuators="all"), jnp.array([0.0, np.pi])
    return cldyn.systems.acrobot(actuators="all"), jnp.array([np.pi, 0.0])


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "acrobot"])
def test_swing_up_from_near_hanging(name):
    (system, joints), q_target = _upright(name)
    target = joints.keypoints(q_target)
    controller = cldyn.EnergyShaping(system, target, kp=5.0, kd=2.0)
    m = joints.num_joints
    x0, xd0 = joints.to_keypoints(jnp.full(m, 0.05), jnp.zeros(m))
    ts = jnp.linspace(0.0, 25.0, 251)
    out = cldyn.simulate(system, x0, xd0, ts, control=controller, rtol=1e-8, atol=1e-8)
    error = jnp.max(jnp.linalg.norm((out.x - target[None, :]).reshape(ts.shape[0], -1, 2), axis=-1), axis=1)
    assert float(error[0]) > 1.0
    assert float(jnp.max(error[-50:])) < SUCCESS_RADIUS  # converged and stays there
    # the controls are those of eq. 32 along the way
    assert out.u.shape == (ts.shape[0], system.num_inputs)
    assert np.allclose(out.u[10], controller(ts[10], out.x[10], out.xd[10]))


def test_literal_eq32_for_a_pendulum_equals_the_projected_form():
    # for a pendulum g = grad q is tangent to the circle, so projecting it changes nothing
    system, joints = cldyn.systems.pendulum()
    target = joints.keypoints(jnp.array([np.pi]))
    x, xd = joints.to_keypoints(jnp.array([0.7]), jnp.array([0.4]))
    projected = cldyn.EnergyShaping(system, target, 5.0, 2.0, damping="output")(0.0, x, xd)
    literal = cldyn.EnergyShaping(system, target, 5.0, 2.0, project=False, damping="output")(0.0, x, xd)
    assert np.allclose(projected, literal, rtol=1e-12)
    # and by hand: torque = L (e_t . (grad V - kp (x - x*))) - kd L^2 qd ... with g = e_t / L
    length, theta = 1.0, 0.7
    e_t = np.array([np.cos(theta), np.sin(theta)])  # d x / d theta, normalised
    grad_v = np.array([0.0, 9.81])
    shaped = grad_v - 5.0 * (np.asarray(x) - np.asarray(target))
    g = e_t / length
    expected = (g @ shaped) / (g @ g) - 2.0 * g @ np.asarray(xd)
    assert np.allclose(literal, expected, rtol=1e-12)
    # keypoint damping: the same shaped term, damping -kd (g . xd) / (g . g)
    keypoint = cldyn.EnergyShaping(system, target, 5.0, 2.0)(0.0, x, xd)
    assert np.allclose(keypoint, (g @ shaped - 2.0 * g @ np.asarray(xd)) / (g @ g), rtol=1e-12)


def test_keypoint_damping_does_not_depend_on_the_gear():
    for gear in (1.0, 4.0):
        system, joints = cldyn.systems.pendulum(gear=gear)
        target = joints.keypoints(jnp.array([np.pi]))
        x, xd = joints.to_keypoints(jnp.array([0.7]), jnp.array([0.4]))
        controller = cldyn.EnergyShaping(system, target, 5.0, 2.0)
        # the torque actually applied, gear * u, is the same for every gear
        torque = gear * controller(0.0, x, xd)
        if gear == 1.0:
            reference = torque
    assert np.allclose(torque, reference, rtol=1e-12)


def test_cartpole_needs_the_tangent_projection():
    # eq. 32 taken literally leaves the cart-pole hanging: the hinge's input direction pushes the
    # cart keypoint too, so the least-squares match in R^k is wrong on the manifold
    (system, joints), q_target = _upright("cartpole")
    target = joints.keypoints(q_target)
    x0, xd0 = joints.to_keypoints(jnp.array([0.05, 0.05]), jnp.zeros(2))
    ts = jnp.linspace(0.0, 20.0, 21)
    literal = cldyn.EnergyShaping(system, target, 5.0, 2.0, project=False, damping="output")
    out = cldyn.simulate(system, x0, xd0, ts, control=literal)
    assert float(jnp.abs(joints.joints(out.x[-1])[1])) < 0.1  # still hanging


def test_energy_shaping_rejects_systems_without_inputs():
    system, joints = cldyn.systems.pendulum(actuated=False)
    with pytest.raises(ValueError, match="needs a system with inputs"):
        cldyn.EnergyShaping(system, jnp.zeros(2))
    system, _ = cldyn.systems.pendulum()
    with pytest.raises(ValueError, match=r"x_target must have shape \(2,\)"):
        cldyn.EnergyShaping(system, jnp.zeros(3))


def test_energy_shaping_batches_and_differentiates():
    system, joints = cldyn.systems.acrobot(actuators="all")
    controller = cldyn.EnergyShaping(system, joints.keypoints(jnp.array([np.pi, 0.0])))
    q = jax.random.uniform(jax.random.key(0), (16, 2), minval=-3, maxval=3)
    x, xd = jax.jit(jax.vmap(joints.to_keypoints))(q, q * 0.1)
    u = jax.jit(jax.vmap(controller, in_axes=(None, 0, 0)))(0.0, x, xd)
    assert u.shape == (16, 2) and bool(jnp.all(jnp.isfinite(u)))
    grad = jax.grad(lambda c: jnp.sum(c(0.0, x[0], xd[0]) ** 2), allow_int=True)
    assert bool(jnp.isfinite(grad(controller).kp))


def test_energy_shaping_computes_in_the_systems_precision():
    # a float32 model (as keyvision's are) under 64-bit mode: the gains and the target follow it,
    # and the control agrees with the float64 controller of the same system to float32 precision
    system, joints = cldyn.systems.pendulum()
    single = jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, system)
    target = joints.keypoints(jnp.array([np.pi]))
    x, xd = joints.to_keypoints(jnp.array([0.3]), jnp.array([0.5]))
    u64 = cldyn.EnergyShaping(system, target)(0.0, x, xd)
    controller = cldyn.EnergyShaping(single, target)
    assert controller.kp.dtype == controller.x_target.dtype == jnp.float32
    u32 = controller(0.0, x.astype(jnp.float32), xd.astype(jnp.float32))
    assert u32.dtype == jnp.float32
    np.testing.assert_allclose(u32, u64, rtol=1e-5)


def _gauge(alpha):
    """The same cart-pole with its Lagrangian and inputs scaled by `alpha` (`M`, `V`, `g` times
    `alpha`): the same motion for the same controls, as a model learnt from images may come out."""
    return cldyn.systems.cartpole(cart_mass=alpha, pole_mass=0.1 * alpha, gears=alpha, actuators="all")


def _closed_loop_eigenvalues(system, controller, target):
    """Eigenvalues of the closed loop linearised at the target, without the zeros of the directions
    off the constraint manifold."""
    k = system.size

    def field(z):
        x, xd = z[:k], z[k:]
        return jnp.concatenate([xd, system.acceleration(x, xd, controller(0.0, x, xd))])

    eigenvalues = np.linalg.eigvals(np.asarray(jax.jacfwd(field)(jnp.concatenate([target, 0 * target]))))
    eigenvalues = eigenvalues[np.abs(eigenvalues) > 1e-6]
    return eigenvalues[np.argsort(eigenvalues.imag, kind="stable")]


@pytest.mark.parametrize("alpha", [1.0, 7.0])
def test_mass_metric_places_every_mode_at_the_roots_of_the_gains(alpha):
    # with V_d and damping weighed by M, every mode near the target obeys e'' + kd e' + kp e = 0:
    # kp = 5, kd = 2 give s = -1 +- 2j (twice: two degrees of freedom), at any scale of the Lagrangian
    system, joints = _gauge(alpha)
    target = joints.keypoints(jnp.array([0.0, np.pi]))
    controller = cldyn.EnergyShaping(system, target, 5.0, 2.0, metric="mass")
    roots = np.array([-1 - 2j, -1 - 2j, -1 + 2j, -1 + 2j])  # s^2 + 2 s + 5 = 0, twice
    np.testing.assert_allclose(_closed_loop_eigenvalues(system, controller, target), roots, atol=1e-6)


def test_mass_metric_controls_do_not_depend_on_the_scale_of_the_lagrangian():
    (one, joints), (seven, _) = _gauge(1.0), _gauge(7.0)
    target = joints.keypoints(jnp.array([0.0, np.pi]))
    x, xd = joints.to_keypoints(jnp.array([0.3, 2.0]), jnp.array([0.5, -1.0]))
    controls = {
        metric: [cldyn.EnergyShaping(s, target, 5.0, 2.0, metric=metric)(0.0, x, xd) for s in (one, seven)]
        for metric in ("euclidean", "mass")
    }
    np.testing.assert_allclose(*controls["mass"], rtol=1e-10)
    # eq. 32 as printed acts differently at each scale: its slowest mode at scale 7 decays at 1/7
    assert not np.allclose(*controls["euclidean"], rtol=1e-2)
    euclidean = cldyn.EnergyShaping(seven, target, 5.0, 2.0)
    assert float(np.max(_closed_loop_eigenvalues(seven, euclidean, target).real)) == pytest.approx(
        -1 / 7, rel=1e-6
    )


def test_mass_metric_needs_keypoint_damping():
    system, joints = cldyn.systems.pendulum()
    target = joints.keypoints(jnp.array([np.pi]))
    with pytest.raises(ValueError, match="needs damping='keypoint'"):
        cldyn.EnergyShaping(system, target, metric="mass", damping="output")
    with pytest.raises(ValueError, match="metric must be 'euclidean' or 'mass'"):
        cldyn.EnergyShaping(system, target, metric="joint")


@pytest.mark.parametrize("tilt", [0.02, -0.05])
def test_trim_removes_the_rest_offset_of_a_tilted_potential(tilt):
    # The controller's model is the true pendulum (point mass m at length L, joint motor) with gravity
    # rotated by `tilt`: its upright sits `tilt` off the true one. With the mass metric the true loop
    # rests where, in the angle d from upright (any orientation, the learnt upright at d_l = +-tilt),
    #   (g / L) (sin d - sin(d - d_l)) = kp sin d,
    # i.e. d ~ (g / L) d_l / kp: the learnt upright's error times the gravity rate over kp. The trim
    # subtracts the constant command at the target, the torque m g L sin(d_l); then d = 0 solves
    #   (g / L) (sin d - sin(d - d_l) - sin d_l) = kp sin d exactly.
    from scipy.optimize import brentq

    g, length, kp = 9.81, 1.0, 5.0
    system, joints = cldyn.systems.pendulum(length=length, gravity=g)
    rotation = jnp.array([[np.cos(tilt), -np.sin(tilt)], [np.sin(tilt), np.cos(tilt)]])
    weights = system.potential.weights
    tilted = eqx.tree_at(lambda s: s.potential.weights, system, rotation.T @ weights)
    upright = jnp.array([np.pi])
    target = joints.keypoints(upright)
    learnt_up = float(joints.joints(length * (rotation.T @ weights) / jnp.linalg.norm(weights))[0])
    d_l = float(np.angle(np.exp(1j * (learnt_up - np.pi))))
    assert abs(abs(d_l) - abs(tilt)) < 1e-9
    rate = g / length
    expected = brentq(lambda d: rate * (np.sin(d) - np.sin(d - d_l)) - kp * np.sin(d), -0.5, 0.5)
    assert abs(expected) > 1.5 * abs(tilt)  # amplified by about rate / kp
    ts = jnp.linspace(0.0, 30.0, 301)
    x0, xd0 = joints.to_keypoints(upright, jnp.zeros(1))
    rests = {}
    for trim in (False, True):
        controller = cldyn.EnergyShaping(tilted, target, kp, 2.0, metric="mass", trim=trim)
        out = cldyn.simulate(system, x0, xd0, ts, control=controller, rtol=1e-9, atol=1e-9)
        rests[trim] = float(np.angle(np.exp(1j * (float(joints.joints(out.x[-1])[0]) - np.pi))))
        assert float(jnp.max(jnp.abs(out.xd[-1]))) < 1e-4  # at rest
    assert rests[False] == pytest.approx(expected, rel=1e-4)
    assert abs(rests[True]) < 1e-6
    # the trimmed command at the target is zero, the untrimmed one the learnt gravity torque there
    at_target = cldyn.EnergyShaping(tilted, target, kp, 2.0, metric="mass")(0.0, target, jnp.zeros(2))
    trimmed = cldyn.EnergyShaping(tilted, target, kp, 2.0, metric="mass", trim=True)
    assert abs(float(at_target[0])) == pytest.approx(m_g_l_sin := g * length * abs(np.sin(tilt)), rel=1e-6)
    assert m_g_l_sin > 0 and abs(float(trimmed(0.0, target, jnp.zeros(2))[0])) < 1e-12


def test_trim_keeps_the_limit_after_the_trim():
    system, joints = cldyn.systems.pendulum()
    target = joints.keypoints(jnp.array([np.pi]))
    x, xd = joints.to_keypoints(jnp.array([0.3]), jnp.array([0.0]))
    free = cldyn.EnergyShaping(system, target, 5.0, 2.0, trim=True)(0.0, x, xd)
    limited = cldyn.EnergyShaping(system, target, 5.0, 2.0, trim=True, limit=0.1)(0.0, x, xd)
    assert abs(float(free[0])) > 0.1 and float(limited[0]) == pytest.approx(np.sign(float(free[0])) * 0.1)
