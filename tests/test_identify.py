"""cldyn.identify: finding the physics a model is missing, without MuJoCo.

The pieces are checked against independent facts (derivatives of known functions, constrained least
squares by brute force, the weak form on exact trajectories); the loop against data integrated in
generalised coordinates by the references of tests/helpers.py, which carry the missing effect as a
joint-space force written independently of cldyn's terms. The MuJoCo acceptance matrix is in
test_identify_mujoco.py.
"""

import functools
import importlib.util
import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import reference_systems, simulate_reference

import cldyn
from cldyn._identify.regression import Normal, fit

DAMPING_RTOL = 0.05  # linear damping beside the quadratic one, on exact data
QUADRATIC_RTOL = 0.15  # the acceptance figure for the new effect
MIN_ROLLOUT_DROP = 5.0
WEAK_RESIDUAL_RTOL = 1e-4  # weak residual of the exact model / inertial forces
SMOOTHING_ATOL = (1e-12, 1e-9, 1e-6)  # a degree-4 polynomial: position, velocity, acceleration
SINE_RTOL = 1e-4
BY_PARTS_RTOL = 1e-4  # the sums of the quadrature against the integrals (2e-5 here)


# -- pieces -------------------------------------------------------------------------------------


def test_smoothing_differentiates_polynomials_exactly_and_sines_accurately():
    dt = 0.01
    t = np.arange(200) * dt
    smoothing = cldyn.Smoothing(window=9, order=4)
    m = smoothing.margin
    poly = 1.0 + 2.0 * t - 3.0 * t**2 + 0.5 * t**4
    x, xd, xdd = smoothing(poly[None, :, None], dt)
    interior = t[m:-m]
    assert np.allclose(x[0, :, 0], poly[m:-m], atol=SMOOTHING_ATOL[0])
    assert np.allclose(xd[0, :, 0], 2 - 6 * interior + 2 * interior**3, atol=SMOOTHING_ATOL[1])
    assert np.allclose(xdd[0, :, 0], -6 + 6 * interior**2, atol=SMOOTHING_ATOL[2])
    omega = 6.0
    x, xd, _ = smoothing(np.sin(omega * t)[None, :, None], dt)
    assert np.max(np.abs(xd[0, :, 0] - omega * np.cos(omega * interior))) < SINE_RTOL * omega


def test_test_functions_integrate_derivatives_by_parts():
    # int psi f' dt = -int psi' f dt for a smooth f: the identity the weak form rests on
    dt = 0.01
    t = np.arange(300) * dt
    tests = cldyn.Smoothing().test_functions(t.size, dt)
    f, fd = np.sin(3 * t) + t**2, 3 * np.cos(3 * t) + 2 * t
    assert np.allclose(tests.psi @ np.ones_like(t), 1.0)
    scale = np.max(np.abs(tests.psi @ fd))
    assert np.max(np.abs(tests.psi @ fd + tests.dpsi @ f)) < BY_PARTS_RTOL * scale


def test_constrained_least_squares_matches_brute_force():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 4))
    b = A @ np.array([0.5, -0.3, 0.2, -0.8]) + 0.01 * rng.normal(size=200)
    normal = Normal(A.T @ A, A.T @ b, float(b @ b), 200)
    signs = [1, 1, 0, 1]
    theta, rss = fit(normal, [0, 1, 2, 3], signs)
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


# -- data from independent references ------------------------------------------------------------


def _hinges(n):
    """The chain's joint coordinates: link 0 against straight down, link i against link i - 1."""
    out = [cldyn.HingeAngle(child=(None, 0))]
    out += [
        cldyn.HingeAngle(child=(i - 1, i), parent=(None if i == 1 else i - 2, i - 1)) for i in range(1, n)
    ]
    return out


def _reference_data(name, force=None, *, runs=16, seconds=3.0, dt=0.01, spread=2.5, control=1.0, seed=0):
    """Runs of a reference chain from random rest states, with one random constant control per run,
    integrated in joint space with `force(q, qd)` added; returns `(system, joints, data, names)`."""
    system, joints, reference = reference_systems()[name]
    n = reference.n
    rng = np.random.default_rng(seed)
    samples = int(round(seconds / dt)) + 1
    q0 = rng.uniform(-spread, spread, size=(runs, n))
    u = rng.uniform(-control, control, size=(runs, system.num_inputs))
    us = np.broadcast_to(u[:, None, :], (runs, samples, system.num_inputs))

    @jax.jit
    def run(q0, us):
        return jax.vmap(
            lambda a, b: simulate_reference(reference, a, jnp.zeros(n), b, dt, samples, force=force)
        )(q0, us)[0]

    x = np.asarray(run(jnp.asarray(q0), jnp.asarray(us)))
    names = ["shoulder", "elbow", "wrist"][:n] if n > 1 else ["hinge"]
    return system, joints, cldyn.Sequences(x, np.array(us), dt), dict(zip(names, _hinges(n)))


@functools.cache
def _effect_free_pendulum():
    return _reference_data("pendulum", runs=4)


def test_weak_residual_of_the_true_model_vanishes():
    from cldyn._identify.residual import Residual, evaluate
    from cldyn._identify.smoothing import prepare

    system, joints, data, coordinates = _effect_free_pendulum()
    smoothing = cldyn.Smoothing()
    prepared = prepare(data.x, data.u, data.dt, smoothing, tuple(coordinates.values()))
    tests = smoothing.test_functions(prepared.x.shape[1], data.dt)
    weak = tests.weak(*evaluate(Residual(system, joints), *prepared.arrays()))
    residual, inertial = weak[..., 0], weak[..., 1]
    assert np.sqrt(np.mean(residual**2)) < WEAK_RESIDUAL_RTOL * np.sqrt(np.mean(inertial**2))


@pytest.mark.slow
def test_identify_finds_linear_and_quadratic_joint_damping(tmp_path):
    # the acceptance figure of the new effect: aerodynamic drag -c |qd| qd on the acrobot's elbow,
    # beside viscous damping -b qd on its shoulder, both integrated in joint space by the reference
    # (not by cldyn's JointDamping or JointQuadraticDamping)
    b, c = 0.05, 0.02
    system, joints, data, coordinates = _reference_data(
        "acrobot", lambda q, qd: jnp.array([-b * qd[0], -c * jnp.abs(qd[1]) * qd[1]]), seed=1
    )
    meter = cldyn.TextProgressMeter(interval=0.0)
    result = cldyn.identify(
        system, data, joint_coordinates=coordinates, joints=joints, bootstrap=40, progress_meter=meter
    )
    found = {(d.name, d.where): d for d in result.detected}
    assert set(found) == {("joint_damping", "shoulder"), ("joint_quadratic_damping", "elbow")}, [
        d.to_dict() for d in result.detected
    ]
    quadratic = found[("joint_quadratic_damping", "elbow")]
    print(f"quadratic damping at the elbow: {quadratic.value:.6g} (truth {c}); "
          f"linear at the shoulder: {found[('joint_damping', 'shoulder')].value:.6g} (truth {b})")
    assert abs(quadratic.value - c) <= QUADRATIC_RTOL * c
    linear = found[("joint_damping", "shoulder")]
    assert abs(linear.value - b) <= DAMPING_RTOL * b
    assert linear.ci[0] <= linear.value <= linear.ci[1]
    assert result.before.rollout_rmse_1s > MIN_ROLLOUT_DROP * result.after.rollout_rmse_1s
    # the augmented model holds the effects as cldyn terms
    terms = result.model.dissipation.terms
    assert [type(t) for t in terms if isinstance(t, cldyn.JointQuadraticDamping | cldyn.JointDamping)] in (
        [cldyn.JointDamping, cldyn.JointQuadraticDamping],
        [cldyn.JointQuadraticDamping, cldyn.JointDamping],
    )
    if importlib.util.find_spec("matplotlib") is None:
        return  # the report's plots need the [vision] extra; everything above is checked without it
    out = result.save(tmp_path / "report")
    report = json.loads((out / "report.json").read_text())
    assert {(d["effect"], d["where"]) for d in report["detected"]} == set(found)
    assert set(report["before"]) >= {"accel_rmse", "rollout_rmse_1s"}
    assert (out / "report.md").read_text().startswith("# Missing physics")
    assert (out / "error_over_time.png").stat().st_size > 10_000
    assert (out / "residual_vs_feature.png").stat().st_size > 10_000


def test_identify_rejects_bad_input():
    system, joints, data, coordinates = _effect_free_pendulum()
    with pytest.raises(ValueError, match=r"x must have shape \(runs, T, 2\)"):
        cldyn.identify(
            system, cldyn.Sequences(data.x[..., :1], data.u, data.dt), joint_coordinates=coordinates
        )
    bad = np.array(data.x)
    bad[2, 10, 0] = np.nan
    with pytest.raises(ValueError, match="x"):
        cldyn.Sequences(bad, data.u, data.dt)
    with pytest.raises(ValueError, match="unknown effect 'magic'"):
        cldyn.identify(system, data, joint_coordinates=coordinates, effects=("magic",))
    with pytest.raises(ValueError, match="more than once"):
        cldyn.identify(
            system, data, joint_coordinates=coordinates, effects=("joint_damping", "joint_damping")
        )
    with pytest.raises(ValueError, match="at least 4 runs"):
        cldyn.identify(system, data.take(slice(0, 3)), joint_coordinates=coordinates)
    with pytest.raises(ValueError, match="holdout"):
        cldyn.identify(system, data, joint_coordinates=coordinates, holdout=1.5)
    with pytest.raises(TypeError, match="Sequences"):
        cldyn.identify(system, np.asarray(data.x), joint_coordinates=coordinates)
