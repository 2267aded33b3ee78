"""cldyn.identify: finding the physics a model is missing.

The fast tests check the pieces against independent facts (derivatives of known functions, the weak
form on exact trajectories, constrained least squares by brute force). The slow tests are the
acceptance matrix: MuJoCo plays reality with an effect the nominal model does not declare.
"""

import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
from cldyn._identify import _fit, _Normal

VALUE_RTOL = 0.15
FRICTION_RTOL = 0.30
MIN_ROLLOUT_DROP = 5.0


# -- pieces -------------------------------------------------------------------------------------


def test_smoothing_differentiates_polynomials_exactly_and_sines_accurately():
    dt = 0.01
    t = np.arange(200) * dt
    smoothing = cldyn.Smoothing(window=9, order=4)
    m = smoothing.margin
    poly = 1.0 + 2.0 * t - 3.0 * t**2 + 0.5 * t**4
    x, xd, xdd = smoothing(poly[None, :, None], dt)
    interior = t[m:-m]
    assert np.allclose(x[0, :, 0], poly[m:-m], atol=1e-12)
    assert np.allclose(xd[0, :, 0], 2 - 6 * interior + 2 * interior**3, atol=1e-9)
    assert np.allclose(xdd[0, :, 0], -6 + 6 * interior**2, atol=1e-6)
    omega = 6.0
    x, xd, _ = smoothing(np.sin(omega * t)[None, :, None], dt)
    assert np.max(np.abs(xd[0, :, 0] - omega * np.cos(omega * interior))) < 1e-4 * omega


def test_constrained_least_squares_matches_brute_force():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 4))
    b = A @ np.array([0.5, -0.3, 0.2, -0.8]) + 0.01 * rng.normal(size=200)
    normal = _Normal(A.T @ A, A.T @ b, float(b @ b), 200)
    signs = [1, 1, 0, 1]
    theta, rss = _fit(normal, [0, 1, 2, 3], signs)
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


def _pendulum_data(damping, runs=16, seconds=3.0, dt=0.01, noise=0.0, seed=0):
    system, joints = cldyn.systems.pendulum(mass=1.0, length=0.8, com=0.5, inertia=0.02)
    truth = system
    if damping:
        truth = cldyn.ConstrainedLagrangian(
            mass=system.mass,
            potential=system.potential,
            constraint=system.constraint,
            input_matrix=system.input_matrix,
            dissipation=cldyn.JointDamping([cldyn.HingeAngle(child=(None, 0))], damping),
        )
    rng = np.random.default_rng(seed)
    ts = jnp.arange(int(round(seconds / dt)) + 1) * dt
    q0 = rng.uniform(-2.5, 2.5, size=(runs, 1))
    u = rng.uniform(-1.0, 1.0, size=(runs, 1))

    @jax.jit
    @jax.vmap
    def run(q0, u):
        x0, xd0 = joints.to_keypoints(q0, jnp.zeros(1))
        return cldyn.simulate(truth, x0, xd0, ts, control=u, rtol=1e-10, atol=1e-10).x

    x = np.asarray(run(jnp.asarray(q0), jnp.asarray(u)))
    x = x + noise * rng.normal(size=x.shape)
    return system, joints, x, np.broadcast_to(u[:, None, :], x.shape[:2] + (1,)), dt


def test_weak_residual_of_the_true_model_vanishes():
    from cldyn._identify import _evaluate, _prepare, _Residual, _test_functions, _weak

    system, joints, x, u, dt = _pendulum_data(0.0, runs=4)
    coordinate = cldyn.HingeAngle(child=(None, 0))
    smoothing = cldyn.Smoothing()
    data = _prepare(x, u, dt, smoothing, (coordinate,))
    tests = _test_functions(data.x.shape[1], smoothing.test_width, smoothing.test_stride, dt)
    arrays = tuple(jnp.asarray(a) for a in (data.x, data.xd, data.u, data.q))
    weak = _weak(_evaluate(_Residual(system, joints), *arrays), *tests)
    residual, inertial = weak[..., 0], weak[..., 1]
    assert np.sqrt(np.mean(residual**2)) < 1e-4 * np.sqrt(np.mean(inertial**2))


def test_identify_finds_damping_in_an_analytic_pendulum(tmp_path):
    system, joints, x, u, dt = _pendulum_data(0.05, runs=16)
    result = cldyn.identify(
        system,
        x,
        u,
        dt,
        joint_coordinates={"hinge": cldyn.HingeAngle(child=(None, 0))},
        joints=joints,
        bootstrap=40,
    )
    assert [d.candidate.label for d in result.detected] == ["joint_damping[hinge]"]
    detection = result.detected[0]
    assert abs(detection.value - 0.05) < 0.01 * 0.05
    assert detection.ci[0] <= detection.value <= detection.ci[1]
    assert result.before["rollout_rmse_1s"] > MIN_ROLLOUT_DROP * result.after["rollout_rmse_1s"]
    # the augmented model holds the effect as a cldyn term
    damping = [t for t in result.model.dissipation.terms if isinstance(t, cldyn.JointDamping)]
    assert len(damping) == 1 and abs(float(damping[0].damping[0]) - 0.05) < 5e-4
    out = result.save(tmp_path / "report")
    report = json.loads((out / "report.json").read_text())
    assert report["detected"][0]["effect"] == "joint_damping"
    assert report["detected"][0]["where"] == "hinge"
    assert set(report["before"]) >= {"accel_rmse", "rollout_rmse_1s"}
    assert (out / "report.md").read_text().startswith("# Missing physics")
    assert (out / "error_over_time.png").stat().st_size > 10_000
    assert (out / "residual_vs_feature.png").stat().st_size > 10_000


def test_identify_rejects_bad_input():
    system, joints, x, u, dt = _pendulum_data(0.0, runs=4, seconds=1.0)
    coords = {"hinge": cldyn.HingeAngle(child=(None, 0))}
    with pytest.raises(ValueError, match=r"x must have shape \(runs, T, 2\)"):
        cldyn.identify(system, x[..., :1], u, dt, joint_coordinates=coords)
    bad = x.copy()
    bad[2, 10, 0] = np.nan
    with pytest.raises(ValueError, match="x contains NaN or infinite values \\(first at run 2, sample 10\\)"):
        cldyn.identify(system, bad, u, dt, joint_coordinates=coords)
    with pytest.raises(ValueError, match="unknown effect 'magic'"):
        cldyn.identify(system, x, u, dt, joint_coordinates=coords, effects=("magic",))
    with pytest.raises(ValueError, match="at least 4 runs"):
        cldyn.identify(system, x[:3], u[:3], dt, joint_coordinates=coords)


# -- the acceptance matrix, against MuJoCo ------------------------------------------------------

mujoco = pytest.importorskip("mujoco")
from cldyn.mujoco import from_mjcf, identify_recording, modify_scene, record  # noqa: E402

# Identification data: KeyCLD's protocol of random initial states and one constant random control per
# run, with control ranges that keep motions within what 100 Hz samples resolve (KeyCLD's +-2 spins
# the pole of its cart-pole at 100 rad/s within a few seconds).
CONTROL_RANGE = {
    "keycld/pendulum": (-0.5, 0.5),
    "keycld/cartpole": (-0.2, 0.2),
    "keycld/acrobot": (-0.5, 0.5),
}
RUNS, SECONDS = 20, 3.0


def _initial(scene, runs, seed, near=None):
    """Random initial states; `near = (joint, centre)` keeps one hinge within 1.5 rad of `centre`
    (a spring's rest), since a keypoint model, a function of the configuration, cannot tell a spring
    wound by a whole turn from an unwound one."""
    bridge = from_mjcf(scene)
    rng = np.random.default_rng(seed)
    qpos = rng.uniform(-np.pi, np.pi, size=(runs, len(bridge.joint_names)))
    for j, name in enumerate(bridge.joint_names):
        if name == "slider":
            qpos[:, j] = rng.uniform(-1, 1, size=runs)
        if near is not None and name == near[0]:
            qpos[:, j] = near[1] + rng.uniform(-1.5, 1.5, size=runs)
    qvel = rng.uniform(-0.1, 0.1, size=qpos.shape)
    return qpos, qvel


def _identify(scene, change, seed, *, noise=0.0, near=None, **kwargs):
    xml = modify_scene(scene, **change)
    data = record(
        xml,
        runs=RUNS,
        duration=SECONDS,
        dt=0.01,
        physics_dt=0.002,
        integrator="rk4",
        seed=seed,
        noise=noise,
        control_range=CONTROL_RANGE[scene],
        initial=_initial(scene, RUNS, seed, near),
    )
    return identify_recording(data, scene, seed=seed, bootstrap=50, **kwargs)


CASES = [
    ("keycld/pendulum", "joint_damping", "hinge", dict(joints={"hinge": {"damping": 0.1}}), 0.1),
    (
        "keycld/pendulum",
        "joint_coulomb",
        "hinge",
        dict(
            joints={"hinge": {"frictionloss": 0.1}}, flags={"constraint": "enable", "frictionloss": "enable"}
        ),
        0.1,
    ),
    (
        "keycld/pendulum",
        "joint_spring",
        "hinge",
        dict(joints={"hinge": {"stiffness": 2.0, "springref": 0.5}}),
        2.0,
    ),
    ("keycld/pendulum", "joint_armature", "hinge", dict(joints={"hinge": {"armature": 0.05}}), 0.05),
    ("keycld/pendulum", "actuator_gain", "torque", dict(actuators={"torque": {"gear": 2.4}}), 1.2),
    ("keycld/cartpole", "joint_damping", "slider", dict(joints={"slider": {"damping": 1.0}}), 1.0),
    ("keycld/cartpole", "joint_damping", "hinge_1", dict(joints={"hinge_1": {"damping": 0.01}}), 0.01),
    (
        "keycld/cartpole",
        "joint_spring",
        "hinge_1",
        dict(joints={"hinge_1": {"stiffness": 1.0, "springref": 10}}),
        1.0,
    ),
    ("keycld/cartpole", "actuator_gain", "slide", dict(actuators={"slide": {"gear": 5.0}}), 1.25),
    ("keycld/acrobot", "joint_damping", "elbow", dict(joints={"elbow": {"damping": 0.1}}), 0.1),
    (
        "keycld/acrobot",
        "joint_coulomb",
        "shoulder",
        dict(
            joints={"shoulder": {"frictionloss": 0.2}},
            flags={"constraint": "enable", "frictionloss": "enable"},
        ),
        0.2,
    ),
    (
        "keycld/acrobot",
        "joint_spring",
        "shoulder",
        dict(joints={"shoulder": {"stiffness": 10.0, "springref": 20}}),
        10.0,
    ),
    ("keycld/acrobot", "joint_armature", "elbow", dict(joints={"elbow": {"armature": 0.05}}), 0.05),
    ("keycld/acrobot", "actuator_gain", "shoulder", dict(actuators={"shoulder": {"gear": 1.6}}), 0.8),
]


def _check(result, effect, where, truth, rtol):
    assert result.detected, f"nothing detected; rejected: {[d.candidate.label for d in result.rejected]}"
    top = result.detected[0]
    assert (top.candidate.effect, top.candidate.where) == (effect, where), [
        d.to_dict() for d in result.detected
    ]
    assert abs(top.value - truth) <= rtol * truth, f"{top.value} vs {truth}"
    drop = result.before["rollout_rmse_1s"] / result.after["rollout_rmse_1s"]
    assert drop >= MIN_ROLLOUT_DROP, f"rollout error {result.before} -> {result.after}"


@pytest.mark.slow
@pytest.mark.parametrize(
    "scene, effect, where, change, truth", CASES, ids=[f"{c[0].split('/')[1]}-{c[1]}-{c[2]}" for c in CASES]
)
def test_injected_effect_is_found(scene, effect, where, change, truth):
    # dm_control's MJCF compiles angles in degrees: springref is given in degrees, reported in radians
    springref = np.radians(change["joints"][where]["springref"]) if effect == "joint_spring" else None
    seed = CASES.index((scene, effect, where, change, truth))
    result = _identify(scene, change, seed, near=(where, springref) if springref is not None else None)
    _check(result, effect, where, truth, FRICTION_RTOL if effect == "joint_coulomb" else VALUE_RTOL)
    if springref is not None:
        assert abs(result.detected[0].parameters["springref"] - springref) < 0.05


@pytest.mark.slow
def test_nothing_is_found_in_effect_free_data():
    found = []
    for seed in range(10):
        result = _identify("keycld/acrobot", {}, 100 + seed)
        found.append([d.candidate.label for d in result.detected])
    assert sum(bool(f) for f in found) <= 1, found


@pytest.mark.slow
def test_two_effects_at_once_are_both_found():
    change = dict(joints={"elbow": {"damping": 0.1}, "shoulder": {"stiffness": 10.0, "springref": 20}})
    result = _identify("keycld/acrobot", change, 7, near=("shoulder", np.radians(20)))
    found = {(d.candidate.effect, d.candidate.where): d.value for d in result.detected}
    assert abs(found[("joint_damping", "elbow")] - 0.1) <= VALUE_RTOL * 0.1
    assert abs(found[("joint_spring", "shoulder")] - 10.0) <= VALUE_RTOL * 10.0
    assert result.before["rollout_rmse_1s"] >= MIN_ROLLOUT_DROP * result.after["rollout_rmse_1s"]


@pytest.mark.slow
@pytest.mark.parametrize(
    "scene, where, damping",
    [("keycld/pendulum", "hinge", 0.1), ("keycld/cartpole", "slider", 1.0), ("keycld/acrobot", "elbow", 0.1)],
)
def test_damping_is_found_through_1mm_noise(scene, where, damping):
    result = _identify(scene, dict(joints={where: {"damping": damping}}), 31, noise=1e-3)
    _check(result, "joint_damping", where, damping, VALUE_RTOL)


@pytest.mark.slow
def test_a_learned_nominal_model_still_leads_to_the_damping():
    # dm_control's stock acrobot declares damping 0.05 on both joints; the nominal model gets a neural
    # potential fitted to these damped data, which it cannot absorb into a conservative force
    import equinox as eqx

    from cldyn._identify import _prepare, _test_functions, refit

    data = record(
        "acrobot",
        runs=RUNS,
        duration=SECONDS,
        dt=0.01,
        physics_dt=0.002,
        integrator="rk4",
        seed=3,
        control_range=(-0.5, 0.5),
    )
    bridge = from_mjcf("acrobot")
    learned = eqx.tree_at(
        lambda s: s.potential, bridge.system, cldyn.MLPPotential(bridge.system.size, key=jax.random.key(0))
    )
    smoothing = cldyn.Smoothing()
    prepared = _prepare(data.x, data.u, data.dt, smoothing, bridge.joint_coordinates)
    tests = _test_functions(prepared.x.shape[1], smoothing.test_width, smoothing.test_stride, data.dt)
    learned = refit(learned, prepared, bridge.joints, np.ones(2), tests)
    result = cldyn.identify(
        learned,
        data.x,
        data.u,
        data.dt,
        joint_coordinates=dict(zip(bridge.joint_names, bridge.joint_coordinates)),
        joints=bridge.joints,
        actuator_names=bridge.actuator_names,
        keypoint_names=bridge.keypoint_names,
        bootstrap=50,
    )
    found = {(d.candidate.effect, d.candidate.where): d.value for d in result.detected}
    assert abs(found[("joint_damping", "elbow")] - 0.05) <= VALUE_RTOL * 0.05
    assert ("joint_damping", "shoulder") in found or any(
        "shoulder" in d.candidate.where for d in result.detected
    )
    assert result.after["rollout_rmse_1s"] < result.before["rollout_rmse_1s"]
