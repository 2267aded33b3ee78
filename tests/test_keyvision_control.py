"""Control from camera frames: the policy's state estimate against a closed form, the closed loop
with MuJoCo in which the policy only ever sees rendered frames, and the renderer setting it relies on."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
import keyvision
from keyvision import _control
from keyvision._cli import main

SIZE = 16


def _tiny_pendulum(size: int = SIZE) -> keyvision.KeyCLD:
    keys = jax.random.split(jax.random.key(0), 3)
    return keyvision.KeyCLD(
        keyvision.KeypointEstimator(1, width=4, image_size=size, key=keys[0]),
        cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=keys[1], width=8),
        keyvision.Renderer(1, width=4, image_size=size, key=keys[2]),
    )


@pytest.mark.parametrize("dt", [0.02, 0.01])
def test_the_velocity_estimate_is_the_tangent_velocity_to_second_order(dt):
    # a keypoint on a circle about the anchor, at constant angular speed: the projected second-order
    # backward difference is tangent to the circle exactly, and within O(dt^2) of r w (-sin, cos)
    policy = keyvision.FramePolicy(_tiny_pendulum(), jnp.array([0.0, 0.4]), dt)
    radius, speed, angle = 0.4, 3.0, 0.7
    angles = angle - speed * dt * np.arange(2, -1, -1)
    memory = jnp.asarray(radius * np.stack([np.cos(angles), np.sin(angles)], axis=1), jnp.float32)
    x, xd = policy.state(memory)
    exact = radius * speed * np.array([-np.sin(angle), np.cos(angle)])
    assert abs(float(jnp.dot(x, xd))) < 1e-6  # tangent: the constraint |x| = const has J = 2 x^T
    error = float(jnp.linalg.norm(xd - exact))
    # the backward difference's error is (dt^2 / 3) |x'''| = (dt^2 / 3) r w^3, the projection removes
    # its radial part
    assert error < 0.5 * dt**2 * radius * speed**3 and error > 1e-3 * dt**2 * radius * speed**3


def test_the_policy_passes_its_metric_to_energy_shaping():
    model = _tiny_pendulum()
    target = jnp.array([0.0, 0.4])
    memory = jnp.asarray([[0.3, 0.2], [0.32, 0.21], [0.33, 0.23]], jnp.float32)
    policy = keyvision.FramePolicy(model, target, 0.02, metric="mass")
    x, xd = policy.state(memory)
    reference = cldyn.EnergyShaping(model.dynamics, target.astype(jnp.float32), 5.0, 2.0, metric="mass")
    np.testing.assert_allclose(policy.controller(0.0, x, xd), reference(0.0, x, xd), rtol=1e-6)
    with pytest.raises(ValueError, match="metric must be"):
        keyvision.FramePolicy(model, target, 0.02, metric="joint")


def test_a_policy_needs_learnt_energy():
    keys = jax.random.split(jax.random.key(1), 3)
    node = keyvision.KeyCLD(
        keyvision.KeypointEstimator(1, width=4, image_size=SIZE, key=keys[0]),
        cldyn.SecondOrderNeuralODE(2, 1, key=keys[1], width=8),
        keyvision.Renderer(1, width=4, image_size=SIZE, key=keys[2]),
    )
    with pytest.raises(TypeError, match="ConstrainedLagrangian"):
        keyvision.FramePolicy(node, jnp.zeros(2), 0.02)
    with pytest.raises(ValueError, match="image_target: the frame has shape"):
        keyvision.image_target(_tiny_pendulum(), jnp.zeros((8, 8, 3)))
    # a 16-bit frame taken for floats in [0, 1] would be far too bright: refused, naming its dtype
    with pytest.raises(TypeError, match="uint8 0..255 or float in \\[0, 1\\], got dtype uint16"):
        keyvision.image_target(_tiny_pendulum(), np.zeros((SIZE, SIZE, 3), np.uint16))


@pytest.mark.mujoco
@pytest.mark.parametrize("scene", ["keycld/pendulum", "keycld/cartpole", "keycld/acrobot"])
def test_a_smaller_shadow_map_renders_the_same_frames(scene):
    # the controller renders with a 512-texel shadow map for speed; at 64 x 64 the frames must be
    # those of the scene's own (2048) that the models were trained on
    mujoco = pytest.importorskip("mujoco")
    xml = keyvision._render._scene_xml(scene)
    frames = []
    for shadow in (None, _control._SHADOW_SIZE):
        setup = _control._scene(xml, keyvision.RenderProtocol(shadow_size=shadow), "fixed", None)
        data = mujoco.MjData(setup.model)
        data.qpos[:] = np.random.default_rng(0).uniform(-1.0, 1.0, setup.model.nq)
        mujoco.mj_forward(setup.model, data)
        renderer = mujoco.Renderer(setup.model, 64, 64)
        renderer.update_scene(data, camera=setup.camera)
        frames.append(renderer.render().copy())
        renderer.close()
    assert frames[0].std() > 5  # a real picture
    np.testing.assert_array_equal(frames[0], frames[1])


@pytest.mark.mujoco
def test_the_closed_loop_policy_sees_only_frames(monkeypatch):
    seen = []
    step = _control._frame_step

    def spy(*args):
        seen.append(args)
        return step(*args)

    monkeypatch.setattr(_control, "_frame_step", spy)
    result = keyvision.swing_up(_tiny_pendulum(), "keycld/pendulum", runs=2, duration=0.1, seed=3, limit=1.0)
    samples = 6  # 0.1 s at 50 frames per second, both ends
    warm_up = 1
    assert len(seen) == warm_up + 2 * samples
    for policy, frame, memory in seen:
        assert isinstance(policy, keyvision.FramePolicy)
        assert frame.dtype == np.uint8 and frame.shape == (SIZE, SIZE, 3)  # a camera frame, nothing else
        assert memory.shape == (3, 2)  # the policy's own keypoints
    assert result["u"].shape == (2, samples, 1) and np.all(np.isfinite(result["u"]))
    assert result["errors"].shape == (2, samples) and result["qpos"].shape == (2, samples, 1)
    # the run starts within 0.2 rad of hanging: every keypoint about a pole length below upright
    assert np.all(result["errors"][:, 0] > 0.9)
    assert len(result["frames"]) == 1 and result["frames"][0].shape == (samples, SIZE, SIZE, 3)
    assert result["steps_per_second"] > 0


@pytest.mark.mujoco
def test_a_second_swing_up_of_a_model_of_the_same_structure_compiles_nothing():
    # JAX keeps every program it compiles (docs/index.md, long processes): a policy that compiled
    # anew per call would hold more memory, and more of the process's memory maps, with every call
    keyvision.swing_up(_tiny_pendulum(), "keycld/pendulum", runs=1, duration=0.04, seed=0)
    compiled = []

    def listen(event, duration, **kwargs):
        del duration
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:  # a model built afresh: new objects, the same structure and shapes
        result = keyvision.swing_up(_tiny_pendulum(), "keycld/pendulum", runs=1, duration=0.04, seed=1)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert result["u"].shape == (1, 3, 1)  # it ran: 0.04 s at 50 frames per second, both ends
    assert compiled == []


@pytest.mark.mujoco
def test_the_state_variant_speaks_the_models_coordinates():
    # observe="state" maps the true keypoints into the model's keypoint frame by an affine fit on
    # rendered poses; on the shipped pendulum model (whose keypoint sits partway along the rod) the
    # mapped upright keypoint is the estimator's target within a small fraction of the image
    model, _ = keyvision.load_model(keyvision._cli._demo.model_directory())
    result = keyvision.swing_up(model, "keycld/pendulum", observe="state", runs=1, duration=0.04)
    assert result["frames"] == []
    hanging = result["x"][0, 0]
    assert np.linalg.norm(hanging - result["target_keypoints"]) > 0.3  # a pole length apart
    radius = np.linalg.norm(result["target_keypoints"] - np.array([0.0, 0.0]))
    assert abs(np.linalg.norm(hanging) - radius) < 0.05  # on the model's circle, not the true one
    assert abs(radius - np.linalg.norm(result["target_true_keypoints"])) > 0.1


def _pendulum_gravity_rate() -> float:
    """m g d / I of MuJoCo's KeyCLD pendulum from its model's numbers: d the distance of the centre of
    mass from the hinge, I the inertia about the hinge (the body's principal inertia about the hinge
    axis plus m d^2, plus the joint's armature)."""
    import mujoco

    physics = mujoco.MjModel.from_xml_string(keyvision._render._scene_xml("keycld/pendulum"))
    (hinge,) = range(physics.njnt)
    body = physics.jnt_bodyid[hinge]
    axis = physics.jnt_axis[hinge]
    offset = physics.body_ipos[body] - physics.jnt_pos[hinge]
    d = np.linalg.norm(offset - np.dot(offset, axis) * axis)
    # the body's inertia frame: principal axes rotated by body_iquat; the hinge axis in that frame
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, physics.body_iquat[body])
    local = rotation.reshape(3, 3).T @ axis
    inertia = float(local @ (physics.body_inertia[body] * local))
    mass = physics.body_mass[body]
    hinge_inertia = inertia + mass * d**2 + physics.dof_armature[hinge]
    return float(mass * np.linalg.norm(physics.opt.gravity) * d / hinge_inertia)


@pytest.mark.mujoco
def test_target_linearisation_without_control_is_the_free_pendulum_at_upright():
    # no learnt potential and no gains: the controller commands nothing, and MuJoCo's pendulum
    # linearised at upright is the inverted pendulum, eigenvalues +- sqrt(m g d / I)
    import equinox as eqx

    model = eqx.tree_at(lambda m: m.dynamics.potential, _tiny_pendulum(), None)
    result = keyvision.target_linearisation(model, "keycld/pendulum", kp=0.0, kd=0.0)
    rate = _pendulum_gravity_rate()
    assert result["gravity_rates"] == pytest.approx([rate], rel=1e-4)
    assert result["largest_real_part"] == pytest.approx(np.sqrt(rate), rel=1e-4)
    _, (low, imaginary) = result["eigenvalues"]  # largest real part first
    assert low == pytest.approx(-np.sqrt(rate), rel=1e-4) and imaginary == 0.0
    assert result["control_at_target"] == pytest.approx([0.0], abs=1e-12)
    assert result["curvature_tolerance"] == 0.0  # kp = 0 tolerates nothing
    # through the camera the same: nothing is commanded whatever the untrained estimator reads; the
    # slopes over +-0.05 rad of sin(q) are below its derivative by (0.05^2 / 6) * 0.85 = 3.5e-4
    frames = keyvision.target_linearisation(model, "keycld/pendulum", observe="frames", kp=0.0, kd=0.0)
    assert frames["largest_real_part"] == pytest.approx(np.sqrt(rate), rel=1e-3)
    assert frames["control_at_target"] == pytest.approx([0.0], abs=1e-12)
    assert frames["observe"] == "frames" and len(frames["camera_gain"]) == 1
    with pytest.raises(ValueError, match="step must be a finite number > 0"):
        keyvision.target_linearisation(model, "keycld/pendulum", step=0.0)
    with pytest.raises(ValueError, match="observe must be 'state' or 'frames'"):
        keyvision.target_linearisation(model, "keycld/pendulum", observe="pixels")


@pytest.mark.mujoco
def test_the_state_variant_aims_at_the_upright_posture_in_its_own_coordinates():
    # with the true state, the target is the upright posture through the same calibration as the
    # state: at rest there, position and velocity errors are zero, and a model without a potential
    # commands nothing whatever the gains. The untrained estimator's reading of the upright frame is
    # off that map by the fit's residual, so a target taken from the frame would pull with kp.
    import equinox as eqx

    model = eqx.tree_at(lambda m: m.dynamics.potential, _tiny_pendulum(), None)
    free = keyvision.target_linearisation(model, "keycld/pendulum", kp=0.0, kd=0.0)
    shaped = keyvision.target_linearisation(model, "keycld/pendulum", kp=5.0, kd=2.0)
    assert shaped["control_at_target"] == pytest.approx([0.0], abs=1e-5)
    assert abs(shaped["largest_real_part"] - free["largest_real_part"]) > 1e-3  # the gains act
    result = keyvision.swing_up(model, "keycld/pendulum", observe="state", runs=1, duration=0.04, kp=5.0)
    frame_target = keyvision.image_target(model, result["target_frame"])
    assert np.linalg.norm(np.asarray(frame_target) - result["target_keypoints"]) > 1e-3


@pytest.mark.mujoco
def test_control_command_writes_its_results_and_the_loop_through_the_camera(tmp_path, capsys):
    imageio = pytest.importorskip("imageio.v3")
    spec = {
        "keypoints": 1,
        "width": 4,
        "image_size": SIZE,
        "dynamics": {
            "kind": "keycld", "size": 2, "num_inputs": 1, "constraint": "pendulum", "width": 8, "depth": 1
        },
        "data": {"scene": "keycld/pendulum"},
    }
    model = keyvision.model_from_spec(spec, key=jax.random.key(0))
    directory, out = keyvision.save_model(tmp_path / "m", model, spec), tmp_path / "out"
    argv = ["control", "--model", str(directory), "--out", str(out), "--duration", "0.1", "--linearise"]
    status = main(argv)
    said, _ = capsys.readouterr()
    assert status == 0
    record = __import__("json").loads((out / "control.json").read_text())
    assert record["runs"] == 1 and len(record["final_error"]) == 1
    loop = record["true_loop"]
    assert loop["observe"] == "frames" and len(loop["camera_gain"]) == 1
    # the scene's gravity, not the model's: MuJoCo's pendulum at upright
    assert loop["gravity_rates"] == pytest.approx([_pendulum_gravity_rate()], rel=1e-4)
    assert "true loop at the target, fed the frames" in said
    frames = imageio.imread(out / "control.gif", index=None)
    assert frames.shape == (6, 4 * SIZE, 4 * SIZE, 3)  # 0.1 s at 0.02 s, both ends, drawn 4x larger
    assert imageio.imread(out / "target.png").shape == (SIZE, SIZE, 3)
    assert (out / "control.png").is_file()


@pytest.mark.mujoco
def test_control_command_refuses_a_target_of_the_wrong_size(tmp_path, capsys):
    imageio = pytest.importorskip("imageio.v3")
    target = tmp_path / "target.png"
    imageio.imwrite(target, np.zeros((32, 32, 3), np.uint8), extension=".png")
    model = keyvision._cli._demo.model_directory()
    status = main(["control", "--model", str(model), "--out", str(tmp_path / "out"), "--target", str(target)])
    _, err = capsys.readouterr()
    assert status == 2
    assert "--target" in err and "(32, 32) pixels" in err
    assert not (tmp_path / "out").exists()
    # grey levels, and a file that is no image: one line each that says what the file is
    imageio.imwrite(target, np.zeros((64, 64), np.uint8), extension=".png")
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    for path, said in ((target, "grey levels; the model takes RGB frames"), (broken, "not a readable image")):
        out = str(tmp_path / "out")
        status = main(["control", "--model", str(model), "--out", out, "--target", str(path)])
        _, err = capsys.readouterr()
        assert status == 2 and said in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()


@pytest.mark.mujoco
def test_target_linearisation_predicts_where_the_state_loop_rests():
    # the linearised rest (-S^-1 a, from the command at the target) against MuJoCo's closed loop run
    # to rest from near hanging (20 s: the slowest mode decays at 1/s); the shipped model's learnt
    # upright is off a little, so the rest is too
    model, _ = keyvision.load_model(keyvision._cli._demo.model_directory())
    for trim in (False, True):
        linear = keyvision.target_linearisation(model, "keycld/pendulum", metric="mass", trim=trim)
        run = keyvision.swing_up(
            model, "keycld/pendulum", observe="state", metric="mass", trim=trim, runs=1, duration=20.0
        )
        assert linear["largest_real_part"] < 0 and run["success"] == [True]
        (offset,) = linear["rest_offset"]
        hanging = np.pi * np.round(run["qpos"][0, 0, 0] / np.pi)  # the run starts within 0.2 rad of it
        rest = float(np.angle(np.exp(1j * (run["qpos"][0, -1, 0] - hanging - np.pi))))  # from upright
        if trim:
            # minus its command at the target, the loop rests at the target (the calibrated upright)
            assert abs(offset) < 1e-6 and linear["rest_error"] < 1e-6
            assert abs(rest) < 1e-4 and run["final_error"][0] < 1e-4
        else:
            assert abs(offset) > 5e-3  # radians
            assert rest == pytest.approx(offset, rel=1e-3)
            assert run["final_error"][0] == pytest.approx(linear["rest_error"], rel=1e-3)
            state = linear
    # seen through the camera the loop rests elsewhere (the estimator's reading near upright is not
    # the calibration's map); the linearisation through the camera predicts that rest, the state's
    # does not. The camera resolves the pose in fractions of a pixel, so not to 1e-3.
    linear = keyvision.target_linearisation(model, "keycld/pendulum", observe="frames", metric="mass")
    run = keyvision.swing_up(model, "keycld/pendulum", metric="mass", runs=1, duration=10.0)
    assert linear["largest_real_part"] < 0 and run["success"] == [True]
    seen = run["final_error"][0]
    assert abs(linear["rest_error"] - seen) < 0.5 * abs(state["rest_error"] - seen)
    assert np.sign(linear["rest_offset"]) == np.sign(state["rest_offset"])
