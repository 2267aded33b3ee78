"""cldyn.energy_balance: joint damping from the balance of energy, against data integrated in generalised
coordinates by the references of tests/helpers.py (the damping there is a joint-space force written
independently of cldyn's terms)."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import reference_systems, simulate_reference

import cldyn

ACROBOT_DAMPING = (0.05, 0.03)
EXACT_RTOL = 0.03  # least squares on exact data (1% here)
INSTRUMENTED_RTOL = 0.10  # instruments on exact data: each velocity from a third of the window (5% here)
NOISY_RTOL = 0.15
FAST_RTOL = 0.25  # 25 Hz sampling of fast turns, the window spanning a turn (measured +14%, +8%)


def _runs(name, force, *, runs=16, seconds=3.0, dt=0.01, seed=0):
    """Runs of a reference from random rest states, one random constant control per run."""
    system, joints, reference = reference_systems()[name]
    n = 2 if name == "cartpole" else reference.n
    rng = np.random.default_rng(seed)
    samples = int(round(seconds / dt)) + 1
    spread = np.array([0.8, 2.5]) if name == "cartpole" else np.full(n, 2.5)
    q0 = rng.uniform(-spread, spread, size=(runs, n))
    u = rng.uniform(-1.0, 1.0, size=(runs, system.num_inputs))
    us = np.broadcast_to(u[:, None, :], (runs, samples, system.num_inputs))

    @jax.jit
    def run(q0, us):
        return jax.vmap(
            lambda a, b: simulate_reference(reference, a, jnp.zeros(n), b, dt, samples, force=force)
        )(q0, us)[0]

    return system, cldyn.Sequences(np.asarray(run(jnp.asarray(q0), jnp.asarray(us))), np.array(us), dt)


def _acrobot_coordinates():
    return {
        "shoulder": cldyn.HingeAngle(child=(None, 0)),
        "elbow": cldyn.HingeAngle(child=(0, 1), parent=(None, 0)),
    }


@functools.cache
def _damped_acrobot():
    return _runs("acrobot", lambda q, qd: -jnp.asarray(ACROBOT_DAMPING) * qd, seed=1)


def _close(balance, truth, rtol):
    assert np.all(np.abs(balance.damping - np.asarray(truth)) <= rtol * np.abs(np.asarray(truth))), (
        balance.summary()
    )


def test_the_balance_finds_the_damping_a_model_lacks():
    system, data = _damped_acrobot()
    coordinates = _acrobot_coordinates()
    exact = cldyn.energy_balance(system, data, joint_coordinates=coordinates, instrumented=False)
    _close(exact, ACROBOT_DAMPING, EXACT_RTOL)
    instrumented = cldyn.energy_balance(system, data, joint_coordinates=coordinates)
    _close(instrumented, ACROBOT_DAMPING, INSTRUMENTED_RTOL)
    assert instrumented.detected == ("shoulder", "elbow")
    assert all(low <= v <= high for v, (low, high) in zip(instrumented.damping, instrumented.interval))
    assert exact.residual_rms < 0.01 * exact.balance_rms, (exact.residual_rms, exact.balance_rms)
    assert instrumented.to_dict()["detected"] == ["shoulder", "elbow"]
    assert "shoulder: damping" in instrumented.summary()


def test_the_balance_is_blind_to_errors_of_the_inertia_and_the_potential():
    # a model with 30% too much mass everywhere and 20% too little gravity: its forces are wrong at
    # every sample (identify's force residual then attributes them to point masses and armature, and
    # its damping with them), but its energy errs only at the windows' ends
    system, data = _damped_acrobot()
    wrong = eqx.tree_at(lambda s: s.potential.weights, system, 0.8 * system.potential.weights)
    heavier = jax.tree.map(lambda a: 1.3 * a if eqx.is_inexact_array(a) else a, wrong.mass)
    wrong = eqx.tree_at(lambda s: s.mass, wrong, heavier)
    balance = cldyn.energy_balance(wrong, data, joint_coordinates=_acrobot_coordinates())
    _close(balance, ACROBOT_DAMPING, INSTRUMENTED_RTOL)
    # with a basis of constant terms only (order 0: a constant inertia, no potential), the error of the
    # inertia's and the potential's shape leaks into the shoulder's damping (27% here)
    blind = cldyn.energy_balance(wrong, data, joint_coordinates=_acrobot_coordinates(), basis_order=0)
    assert abs(blind.damping[0] - ACROBOT_DAMPING[0]) > 2 * INSTRUMENTED_RTOL * ACROBOT_DAMPING[0], (
        blind.summary()
    )


def test_the_balance_counts_the_damping_the_model_already_has():
    system, data = _damped_acrobot()
    shoulder = _acrobot_coordinates()["shoulder"]
    partial = eqx.tree_at(
        lambda s: s.dissipation,
        system,
        cldyn.JointDamping([shoulder], jnp.array([0.02])),
        is_leaf=lambda a: a is None,
    )
    balance = cldyn.energy_balance(
        partial, data, joint_coordinates=_acrobot_coordinates(), instrumented=False
    )
    _close(balance, (ACROBOT_DAMPING[0] - 0.02, ACROBOT_DAMPING[1]), EXACT_RTOL)


def test_the_balance_finds_nothing_on_damping_free_runs():
    system, data = _runs("acrobot", None, seed=2)
    balance = cldyn.energy_balance(system, data, joint_coordinates=_acrobot_coordinates())
    assert balance.detected == (), balance.summary()
    assert all(low <= 0.0 <= high for low, high in balance.interval), balance.summary()


def test_the_balance_reads_a_slider_and_a_hinge():
    # the cart-pole: Legendre terms of the slider's position beside the hinge's Fourier terms
    damping = (0.4, 0.02)  # N s/m on the rail, N m s at the hinge
    system, data = _runs("cartpole", lambda q, qd: -jnp.asarray(damping) * qd, seed=3)
    coordinates = {"slider": cldyn.SliderPosition(0), "hinge": cldyn.HingeAngle(child=(0, 1))}
    balance = cldyn.energy_balance(system, data, joint_coordinates=coordinates)
    _close(balance, damping, INSTRUMENTED_RTOL)


@pytest.mark.parametrize("thinned", [False, True])
def test_the_balance_under_white_noise_at_two_rates(thinned):
    # one recording of a damped pendulum at 1 kHz with 1 mm of noise, as it is and thinned to 100 Hz
    b = 0.1
    system, fast = _runs("pendulum", lambda q, qd: -b * qd, runs=12, dt=0.001, seed=4)
    x = np.asarray(fast.x) + 0.001 * np.random.default_rng(5).standard_normal(fast.x.shape)
    data = (
        cldyn.Sequences(x[:, ::10], fast.u[:, ::10], 0.01) if thinned else cldyn.Sequences(x, fast.u, 0.001)
    )
    balance = cldyn.energy_balance(
        system, data, joint_coordinates={"hinge": cldyn.HingeAngle(child=(None, 0))}
    )
    _close(balance, (b,), NOISY_RTOL)


def test_the_balance_smooths_fast_turns_in_joint_coordinates():
    # sampled coarsely for the speed of the turns (a third of a radian per sample and more), a polynomial
    # through the keypoints' arcs misreads their velocities, the more the faster: measured here, the
    # damped acrobot at 25 Hz through the keypoints reads (0.011, 0.048), and the damping-free one at 50 Hz
    # a spurious elbow damping of 0.023 [0.002, 0.035]; through the joint coordinates (0.057, 0.032) and
    # 0.0016 [-0.0007, 0.0065]
    _, joints, _ = reference_systems()["acrobot"]
    coordinates = dict(zip(joints.names, _acrobot_coordinates().values()))
    system, damped = _runs(
        "acrobot", lambda q, qd: -jnp.asarray(ACROBOT_DAMPING) * qd, dt=0.04, seconds=6.0, seed=3
    )
    angles = np.unwrap(np.asarray(jax.vmap(jax.vmap(joints.joints))(jnp.asarray(damped.x))), axis=1)
    assert np.percentile(np.abs(np.diff(angles, axis=1)), 95) > 0.3  # the premise: fast turns
    balance = cldyn.energy_balance(system, damped, joint_coordinates=coordinates, joints=joints)
    assert balance.joint_space and "joint coordinates" in balance.summary()
    _close(balance, ACROBOT_DAMPING, FAST_RTOL)
    _, free = _runs("acrobot", None, dt=0.02, seconds=6.0, seed=3)
    balance = cldyn.energy_balance(system, free, joint_coordinates=coordinates, joints=joints)
    assert balance.detected == (), balance.summary()


def test_the_balance_rejects_bad_input():
    system, data = _damped_acrobot()
    coordinates = _acrobot_coordinates()
    with pytest.raises(ValueError, match=r"x must have shape \(runs, T, 4\)"):
        cldyn.energy_balance(
            system, cldyn.Sequences(data.x[..., :2], data.u, data.dt), joint_coordinates=coordinates
        )
    with pytest.raises(ValueError, match="at least 4 runs"):
        cldyn.energy_balance(
            system, cldyn.Sequences(data.x[:3], data.u[:3], data.dt), joint_coordinates=coordinates
        )
    with pytest.raises(ValueError, match="too short"):
        cldyn.energy_balance(
            system, cldyn.Sequences(data.x[:, :12], data.u[:, :12], data.dt), joint_coordinates=coordinates
        )
    with pytest.raises(TypeError, match="joint.coordinate"):
        cldyn.energy_balance(system, data, joint_coordinates={"shoulder": lambda x: x[0]})
    _, joints, _ = reference_systems()["acrobot"]
    with pytest.raises(ValueError, match="same joints in the same order"):
        cldyn.energy_balance(system, data, joint_coordinates=coordinates, joints=joints)
    with pytest.raises(TypeError, match="JointMap"):
        cldyn.energy_balance(system, data, joint_coordinates=coordinates, joints=joints.forward)


@pytest.mark.mujoco
def test_the_balance_reads_mujocos_damping_through_noise():
    # MuJoCo as reality: the KeyCLD acrobot with dm_control's stock damping (0.05 N m s at both joints),
    # recorded through 1 mm of noise, against the damping-free MJCF through from_mjcf
    pytest.importorskip("mujoco")
    from cldyn.mujoco import from_mjcf, modify_scene, record

    damping = 0.05
    xml = modify_scene("keycld/acrobot", joints={j: {"damping": damping} for j in ("shoulder", "elbow")})
    data = record(
        xml,
        runs=20,
        duration=3.0,
        dt=0.01,
        physics_dt=0.002,
        integrator="rk4",
        noise=0.001,
        control_range=(-0.5, 0.5),
        seed=0,
    )
    bridge = from_mjcf("keycld/acrobot")
    coordinates = dict(zip(bridge.joint_names, bridge.joint_coordinates))
    balance = cldyn.energy_balance(bridge.system, data, joint_coordinates=coordinates)
    print(balance.summary())
    _close(balance, (damping, damping), NOISY_RTOL)
    assert balance.detected == ("shoulder", "elbow")
