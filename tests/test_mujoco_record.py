"""`record`: what MuJoCo did, saved and loaded, and consistent with itself."""

import json

import numpy as np
import pytest

import cldyn
from cldyn import Sequences

mujoco = pytest.importorskip("mujoco")

from cldyn._cli import main  # noqa: E402
from cldyn.mujoco import record, scene_xml  # noqa: E402

pytestmark = pytest.mark.mujoco

EQUATION_ATOL = 1e-8  # M qacc + qfrc_bias = qfrc_actuator + qfrc_passive + qfrc_constraint
DIFFERENCE_RTOL = 1e-4  # keypoint velocities and accelerations against finite differences


def _model(recording: Sequences) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(recording.info["mjcf_xml"])


def _equation_residual(recording: Sequences) -> float:
    """`M(q) qacc + qfrc_bias - (actuator + passive + constraint)`, with `M` from MuJoCo."""
    model = _model(recording)
    data = mujoco.MjData(model)
    mass = np.zeros((model.nv, model.nv))
    worst = 0.0
    extras = recording.extras
    for r in range(recording.num_runs):
        for s in range(recording.num_samples):
            data.qpos[:] = extras["qpos"][r, s]
            mujoco.mj_forward(model, data)
            mujoco.mj_fullM(model, data, mass)
            lhs = mass @ extras["qacc"][r, s] + extras["qfrc_bias"][r, s]
            applied = ("qfrc_actuator", "qfrc_passive", "qfrc_constraint")
            rhs = sum(extras[name][r, s] for name in applied)
            worst = max(worst, float(np.max(np.abs(lhs - rhs))))
    return worst


@pytest.mark.parametrize("mjcf", ["keycld/acrobot", "cartpole", "pendulum"])
def test_recorded_forces_are_consistent(mjcf):
    # the stock cartpole runs into its rail limit: a constraint force that must balance too
    recording = record(
        mjcf, runs=4, duration=2.0, dt=0.05, seed=3, control=1.0 if mjcf == "cartpole" else "random"
    )
    if mjcf == "cartpole":
        assert np.any(recording.extras["qfrc_constraint"] != 0)
    assert _equation_residual(recording) < EQUATION_ATOL


def test_schema_and_protocol():
    recording = record("keycld/cartpole", runs=50, duration=0.1, dt=0.01, seed=7)
    runs, samples = 50, 11
    extras, info = recording.extras, recording.info
    assert isinstance(recording, Sequences) and recording.dt == 0.01
    assert recording.ts.shape == (samples,)
    np.testing.assert_allclose(recording.ts, np.arange(samples) * 0.01)
    assert extras["qpos"].shape == (runs, samples, 2) and extras["qacc"].shape == (runs, samples, 2)
    for name in ("qvel", "qfrc_passive", "qfrc_actuator", "qfrc_constraint", "qfrc_bias"):
        assert extras[name].shape == (runs, samples, 2) and extras[name].dtype == np.float64
    assert recording.x.shape == recording.xdd.shape == extras["x_clean"].shape == (runs, samples, 4)
    assert recording.u.shape == (runs, samples, 2)
    assert info["keypoint_names"] == ("slider+hinge_1", "pole_1_end")
    assert info["joint_names"] == ("slider", "hinge_1") and info["actuator_names"] == ("slide", "hinge_1")
    assert info["keypoint_dim"] == 2 and info["integrator"] == "RK4" and info["seed"] == 7
    assert np.asarray(info["basis"]).shape == (2, 3) and info["mjcf"] == "keycld/cartpole"
    # nothing was clamped (no control range), so no separate commanded controls
    assert "u_commanded" not in extras
    # KeyCLD's protocol: constant controls in (-2, 2) (no control range in these scenes), zero in 20%
    assert np.all(recording.u == recording.u[:, :1])
    zero = np.all(recording.u[:, 0] == 0, axis=1)
    assert zero.sum() == 10
    assert np.all(np.abs(recording.u[~zero]) < 2) and np.all(recording.u[~zero] != 0)
    assert np.all(np.abs(extras["qpos"][:, 0, 0]) <= 1) and np.all(np.abs(extras["qpos"][:, 0, 1]) <= np.pi)
    assert np.all(np.abs(extras["qvel"][:, 0]) <= 0.1)
    assert np.array_equal(recording.x, extras["x_clean"])


def test_control_forms_and_clamping():
    qpos = np.array([0.2, -0.3])
    start = (qpos, np.zeros(2))
    policy = record("cartpole", duration=0.05, dt=0.01, initial=start, control=lambda t, q, v: [-10.0 * q[0]])
    # the stock cartpole clamps its control to [-1, 1]: what was applied is recorded, and what was
    # commanded beside it
    np.testing.assert_allclose(policy.u[0, 0], [-1.0])
    np.testing.assert_allclose(policy.extras["u_commanded"][0, 0], [-10.0 * 0.2])
    np.testing.assert_allclose(policy.extras["qfrc_actuator"][0, 0, 0], -10.0)  # gear 10
    within = np.abs(policy.extras["u_commanded"]) <= 1
    np.testing.assert_array_equal(policy.u[within], policy.extras["u_commanded"][within])
    series = np.linspace(-0.5, 0.5, 6)[None, :, None]
    timed = record("cartpole", duration=0.05, dt=0.01, initial=start, control=series)
    np.testing.assert_allclose(timed.u[0, :, 0], series[0, :, 0])
    per_run = record("keycld/acrobot", duration=0.02, dt=0.01, control=[[0.1, 0.2], [0.3, 0.4]], seed=1)
    assert per_run.num_runs == 2
    np.testing.assert_allclose(per_run.u[1, -1], [0.3, 0.4])
    zero = record("keycld/acrobot", duration=0.02, dt=0.01, control=None)
    assert not np.any(zero.u) and not np.any(zero.extras["qfrc_actuator"])
    with pytest.raises(ValueError, match="control must have shape"):
        record("keycld/acrobot", duration=0.02, dt=0.01, control=np.zeros((1, 7, 2)))


def test_noise_seed_and_substeps():
    clean = record("keycld/pendulum", runs=20, duration=0.2, dt=0.02, seed=5)
    noisy = record("keycld/pendulum", runs=20, duration=0.2, dt=0.02, seed=5, noise=0.01)
    np.testing.assert_array_equal(noisy.extras["x_clean"], clean.extras["x_clean"])
    assert np.std(noisy.x - noisy.extras["x_clean"]) == pytest.approx(0.01, rel=0.1)
    assert noisy.info["noise"] == 0.01 and clean.info["noise"] == 0.0
    other = record("keycld/pendulum", runs=20, duration=0.2, dt=0.02, seed=6)
    assert not np.allclose(other.extras["qpos"][:, 0], clean.extras["qpos"][:, 0])
    fine = record("keycld/pendulum", runs=2, duration=0.2, dt=0.02, physics_dt=0.005, integrator="rk4")
    assert fine.info["physics_dt"] == 0.005 and fine.info["integrator"] == "RK4"
    with pytest.raises(ValueError, match="whole multiple"):
        record("keycld/pendulum", duration=0.2, dt=0.02, physics_dt=0.003)
    for bad in ({"noise": float("nan")}, {"noise": -0.1}, {"physics_dt": 0.0}, {"duration": float("inf")},
                {"dt": -0.02}, {"runs": 0}, {"seed": -1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            record("keycld/pendulum", **{"duration": 0.2, "dt": 0.02, **bad})


def test_keypoint_derivatives_match_finite_differences():
    """MuJoCo's own consistency: `xd` and `J qacc + Jdot qvel` against differences of the samples."""
    dt = 1e-3
    recording = record(
        "keycld/acrobot", runs=2, duration=0.2, dt=dt, physics_dt=1e-4, integrator="rk4", seed=2
    )
    velocity = (recording.x[:, 2:] - recording.x[:, :-2]) / (2 * dt)
    acceleration = (recording.xd[:, 2:] - recording.xd[:, :-2]) / (2 * dt)
    scale_v, scale_a = np.abs(recording.xd).max(), np.abs(recording.xdd).max()
    assert np.abs(velocity - recording.xd[:, 1:-1]).max() < DIFFERENCE_RTOL * scale_v
    assert np.abs(acceleration - recording.xdd[:, 1:-1]).max() < DIFFERENCE_RTOL * scale_a


def test_save_load(tmp_path):
    recording = record("keycld/acrobot", runs=3, duration=0.05, dt=0.01, noise=0.001, seed=11)
    path = recording.save(tmp_path / "acrobot")
    assert path.name == "acrobot.npz"
    loaded = Sequences.load(path)
    for name in ("x", "xd", "xdd", "u"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(recording, name))
    assert sorted(loaded.extras) == sorted(recording.extras)
    for name, value in recording.extras.items():
        np.testing.assert_array_equal(loaded.extras[name], value)
        assert loaded.extras[name].dtype == value.dtype
    assert loaded.info == recording.info and loaded.dt == recording.dt
    mujoco.MjModel.from_xml_string(loaded.info["mjcf_xml"])  # the scene travels with the data
    with pytest.raises(FileExistsError, match="acrobot.npz"):
        recording.save(path)


_RECORDED = (
    "qpos", "qvel", "qacc", "x_clean", "qfrc_passive", "qfrc_actuator", "qfrc_constraint", "qfrc_bias",
)


def _legacy_recording(recording: Sequences, path) -> None:
    """A file as `cldyn.mujoco.Recording.save` wrote it before recordings became `Sequences`."""
    info = recording.info
    metadata = {"schema": "cldyn.mujoco.Recording/1", "dt": recording.dt}
    for key in ("keypoint_names", "joint_names", "actuator_names", "mjcf", "mjcf_xml", "physics_dt",
                "integrator", "noise", "seed"):
        metadata[key] = list(info[key]) if isinstance(info[key], tuple) else info[key]
    arrays = {name: recording.extras[name] for name in _RECORDED}
    np.savez_compressed(
        path, time=recording.ts, x=recording.x, xd=recording.xd, xdd=recording.xdd, u=recording.u,
        basis=np.asarray(info["basis"]), metadata=np.array(json.dumps(metadata)), **arrays,
    )


def test_old_recording_files_load(tmp_path):
    recording = record("keycld/cartpole", runs=2, duration=0.03, dt=0.01, noise=0.001, seed=4)
    _legacy_recording(recording, tmp_path / "old.npz")
    loaded = cldyn.Sequences.load(tmp_path / "old.npz")
    for name in ("x", "xd", "xdd", "u"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(recording, name))
    for name, value in recording.extras.items():
        np.testing.assert_array_equal(loaded.extras[name], value)
    assert loaded.info == recording.info
    # the old files stored the sample times beside dt: the two must agree
    with np.load(tmp_path / "old.npz") as npz:
        contents = dict(npz)
    contents["time"] = contents["time"] * 2
    np.savez(tmp_path / "times.npz", **contents)
    with pytest.raises(ValueError, match="times.npz: the times are not multiples of the metadata's dt"):
        cldyn.Sequences.load(tmp_path / "times.npz")
    del contents["qfrc_bias"]
    np.savez(tmp_path / "partial.npz", **contents)
    with pytest.raises(ValueError, match=r"partial.npz: missing arrays \['qfrc_bias'\]"):
        cldyn.Sequences.load(tmp_path / "partial.npz")


def test_non_planar_models_record_world_keypoints():
    xml = """<mujoco><worldbody><body pos="0 0 1"><joint name="ball" type="ball"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 -1" size=".05"/></body></worldbody></mujoco>"""
    recording = record(xml, runs=2, duration=0.02, dt=0.01, initial=None)
    assert recording.info["keypoint_dim"] == 3 and recording.info["basis"] == ()
    assert recording.x.shape == (2, 3, 3) and recording.extras["qpos"].shape == (2, 3, 4)
    np.testing.assert_allclose(recording.x[0, 0], [0.3, 0.0, 0.0], atol=1e-12)


def test_command_line(tmp_path, capsys):
    out = tmp_path / "data.npz"
    assert (
        main(
            [
                "record",
                "--mjcf",
                "keycld/pendulum",
                "--out",
                str(out),
                "--runs",
                "5",
                "--duration",
                "0.1",
                "--dt",
                "0.02",
                "--noise",
                "0.01",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    recording = Sequences.load(out)
    assert recording.num_runs == 5 and recording.num_samples == 6 and recording.info["seed"] == 3
    assert recording.info["noise"] == 0.01
    assert "wrote" in capsys.readouterr().out

    report_dir = tmp_path / "validation"
    status = main(
        [
            "validate",
            "--mjcf",
            "keycld/pendulum",
            "--out",
            str(report_dir),
            "--runs",
            "2",
            "--duration",
            "0.2",
            "--physics-dt",
            "1e-3",
            "--tolerance",
            "1e-6",
        ]
    )
    assert status == 0
    report = json.loads((report_dir / "validation.json").read_text())
    assert report["duration"] == 0.2 and report["max_position_error"] < 1e-6
    assert (report_dir / "keypoint_error.png").stat().st_size > 0
    assert main(["record", "--mjcf", "no_such_file.xml", "--out", str(tmp_path / "other.npz")]) == 2
    assert "MJCF file not found: no_such_file.xml" in capsys.readouterr().err


def test_applied_controls_include_force_clamping():
    # a motor whose force MuJoCo clamps to forcerange: the recorded control is the force applied over
    # the gain (gear * u is then MuJoCo's joint force), the commanded one is kept beside it
    xml = scene_xml("keycld/pendulum").replace(
        'ctrllimited="false"',
        'ctrllimited="true" ctrlrange="-1.5 1.5" forcelimited="true" forcerange="-0.3 0.3"',
    )
    commands = np.array([[2.0], [-1.0], [0.2]])
    data = record(xml, duration=0.1, dt=0.01, control=commands, seed=0)
    np.testing.assert_allclose(data.u[:, 0, 0], [0.3, -0.3, 0.2])
    np.testing.assert_allclose(data.extras["u_commanded"][:, 0, 0], commands[:, 0])
    gear = 2.0  # the scene's motor
    np.testing.assert_allclose(data.extras["qfrc_actuator"][..., 0], gear * data.u[..., 0], rtol=1e-12)
