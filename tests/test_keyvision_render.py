"""Rendering datasets with MuJoCo: the camera map against rendered pixels, the protocol, the cache."""

import dataclasses
import os
import subprocess
import sys

import equinox as eqx
import jax
import numpy as np
import pytest

pytest.importorskip("mujoco")

import cldyn
import keyvision
import keyvision._render as render_module

pytestmark = pytest.mark.mujoco

PIXEL_TOL = 0.35  # pixels: a rendered sphere's centroid against the projection of its centre
EXACT = 1e-9
ARM = 0.4  # the marker scene's arm length
PIVOT_HEIGHT = 0.3
CAMERA = [0.5, -2.2, 1.0]


def _look_at(position, target, roll):
    z = np.asarray(position, float) - target
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    x, y = np.cos(roll) * x + np.sin(roll) * y, -np.sin(roll) * x + np.cos(roll) * y
    return " ".join(f"{v:.12f}" for v in (*x, *y))


# A white, unlit sphere on an arm (hinge) that rides a carriage (slide), on black, seen by a camera
# that looks at the plane obliquely and rolled: the pixel-to-plane map is then truly projective.
MARKER_SCENE = f"""
<mujoco model="marker">
  <visual><headlight ambient="0 0 0" diffuse="0 0 0" specular="0 0 0"/></visual>
  <asset><material name="glow" rgba="1 1 1 1" emission="1"/></asset>
  <option timestep="0.01" integrator="RK4"/>
  <worldbody>
    <camera name="oblique" pos="0.5 -2.2 1.0" xyaxes="{_look_at(CAMERA, [0, 0, PIVOT_HEIGHT], 0.3)}"/>
    <camera name="follow" mode="trackcom" pos="0 -2 0.3"/>
    <body name="carriage" pos="0 0 {PIVOT_HEIGHT}">
      <joint name="slide" type="slide" axis="1 0 0"/>
      <geom type="sphere" size="0.02" mass="1" group="3"/>
      <body name="arm">
        <joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom type="sphere" pos="0 0 {ARM}" size="0.035" material="glow" mass="0.5"/>
        <site name="marker" pos="0 0 {ARM}" size="0.01" group="5"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="slide"/><motor joint="hinge"/></actuator>
</mujoco>
"""
SMALL = keyvision.RenderProtocol(runs=3, frames=4, validation_runs=1, slide_limit=0.3)


@pytest.fixture(scope="module")
def marker_frames():
    return keyvision.render(
        MARKER_SCENE, camera="oblique", protocol=SMALL, keypoints=["marker"], cache=False, workers=1
    )


def test_scene_constraint_refuses_a_camera_that_sees_the_plane_in_perspective(marker_frames):
    # the oblique camera's map is projective: a rod's length in the plane is no length in the image
    with pytest.raises(ValueError, match="perspective"):
        keyvision.scene_constraint(marker_frames)


# A cart on a rail inclined along (0.8, 0, 0.6), a pole hinged on it; the camera looks straight at the
# plane from 4 m (MuJoCo's fovy of 45 degrees)
INCLINED_SCENE = """
<mujoco model="inclined">
  <option timestep="0.01" integrator="RK4"><flag contact="disable"/></option>
  <worldbody>
    <light pos="0 -1 4" dir="0 0 -1"/>
    <camera name="fixed" pos="0 -4 1" zaxis="0 -1 0"/>
    <body name="cart" pos="0 0 1">
      <joint name="rail" type="slide" axis="0.8 0 0.6"/>
      <geom type="box" size="0.1 0.05 0.05" mass="1" rgba="1 0 0 1"/>
      <body name="pole">
        <joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.03" mass="0.3" rgba="0 1 0 1"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="rail"/></actuator>
</mujoco>
"""


def test_scene_constraint_carries_a_rail_at_an_angle_to_the_image(tmp_path):
    from cldyn._keycld import constraint_entries

    protocol = keyvision.RenderProtocol(runs=3, frames=6, validation_runs=1, image_size=16, slide_limit=0.3)
    frames = keyvision.render(INCLINED_SCENE, protocol=protocol, cache=False, workers=1)
    constraint = keyvision.scene_constraint(frames)
    rod, rail = constraint.constraints
    assert rod == cldyn.Distance(0, 1) and isinstance(rail, cldyn.LinearConstraint)
    # one row on the cart's keypoint: the rail's normal (-0.6, 0.8), in image units (metres per unit
    # 4 tan(22.5 degrees) for a camera 4 m from the plane)
    metres_per_unit = 4 * np.tan(np.radians(22.5))
    np.testing.assert_allclose(rail.rows, [[-0.6 * metres_per_unit, 0.8 * metres_per_unit, 0, 0]], rtol=1e-6)
    # the true keypoints seen in the image keep it along every run
    seen = frames.camera.to_image(frames.extras["keypoints"].reshape(-1, 2, 2)).reshape(3, 6, 4)
    values = np.asarray(seen @ np.asarray(rail.rows)[0])
    np.testing.assert_allclose(values, values[:, :1].repeat(6, axis=1), atol=1e-6)
    # a model's spec records it (what keyvision train writes); saved and loaded, the model has it
    dynamics = {"kind": "keycld", "size": 4, "num_inputs": 1, "width": 4, "depth": 1}
    dynamics["constraint"] = constraint_entries(constraint)
    assert dynamics["constraint"][1]["linear"] == [[float(v) for v in np.asarray(rail.rows)[0]]]
    spec = {"keypoints": 2, "image_size": 16, "width": 4, "dynamics": dynamics}
    keyvision.save_model(tmp_path, keyvision.model_from_spec(spec, key=jax.random.key(0)), spec)
    loaded, _ = keyvision.load_model(tmp_path)
    rod_loaded, rail_loaded = loaded.dynamics.constraint.constraints  # in the model's float32
    assert rod_loaded == rod and isinstance(rail_loaded, cldyn.LinearConstraint)
    np.testing.assert_allclose(rail_loaded.rows, rail.rows, rtol=1e-7)


# A bead that slides along a swinging arm (a slide on a turning body), the arm hinged at (0, 1)
BEAD_SCENE = """
<mujoco model="bead">
  <option timestep="0.01" integrator="RK4"><flag contact="disable"/></option>
  <worldbody>
    <light pos="0 -1 4" dir="0 0 -1"/>
    <camera name="fixed" pos="0.2 -4 0.8" zaxis="0 -1 0"/>
    <body name="arm" pos="0 0 1">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.8" size="0.02" mass="0.5" rgba="0 1 0 1"/>
      <site name="tip" pos="0 0 -0.8"/>
      <body name="bead" pos="0 0 -0.4">
        <joint name="slide" type="slide" axis="0 0 1"/>
        <geom type="sphere" size="0.06" mass="0.3" rgba="1 0 0 1"/>
        <site name="bead"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="hinge"/></actuator>
</mujoco>
"""


def test_scene_constraint_carries_a_slide_on_a_turning_body_to_the_image(tmp_path):
    from cldyn._keycld import constraint_entries

    protocol = keyvision.RenderProtocol(runs=3, frames=6, validation_runs=1, image_size=16, slide_limit=0.2)
    frames = keyvision.render(
        BEAD_SCENE, protocol=protocol, keypoints=["bead", "tip"], cache=False, workers=1
    )
    pivot, slide = keyvision.scene_constraint(frames).constraints
    # the arm's end pivots about the hinge as the image sees it (the camera centred on (0.2, 0.8))
    metres_per_unit = 4 * np.tan(np.radians(22.5))
    assert pivot.keypoint == 1
    np.testing.assert_allclose(pivot.point, np.array([-0.2, 0.2]) / metres_per_unit, atol=1e-9)
    # the bead stays on the line from the pivot through the arm's end: at any keypoints, the slide's
    # constraint is a fixed multiple of the cross product of the two (the bead's offset across the arm)
    x = np.random.default_rng(0).normal(size=(20, 4))
    bead, arm = x[:, :2] - pivot.point, x[:, 2:] - pivot.point
    cross = arm[:, 0] * bead[:, 1] - arm[:, 1] * bead[:, 0]
    values = np.asarray(jax.vmap(slide)(jax.numpy.asarray(x)))[:, 0]
    factor = values @ cross / (cross @ cross)
    assert abs(factor) > 0.1
    np.testing.assert_allclose(values, factor * cross, rtol=1e-9, atol=1e-12)
    seen = frames.camera.to_image(frames.extras["keypoints"].reshape(-1, 2, 2)).reshape(-1, 4)
    np.testing.assert_allclose(np.asarray(jax.vmap(slide)(jax.numpy.asarray(seen))), 0.0, atol=1e-9)
    # its affine maps are the scene's geometry: no gradient reaches them, so training leaves them be
    grads = eqx.filter_grad(lambda c: jax.numpy.sum(jax.vmap(c)(jax.numpy.asarray(x)) ** 2))(slide)
    assert all(np.all(np.asarray(g) == 0) for g in jax.tree.leaves(grads))
    # recorded in a model's spec, saved and loaded
    dynamics = {"kind": "keycld", "size": 4, "num_inputs": 1, "width": 4, "depth": 1}
    dynamics["constraint"] = constraint_entries(keyvision.scene_constraint(frames))
    spec = {"keypoints": 2, "image_size": 16, "width": 4, "dynamics": dynamics}
    keyvision.save_model(tmp_path, keyvision.model_from_spec(spec, key=jax.random.key(0)), spec)
    loaded, _ = keyvision.load_model(tmp_path)
    loaded_values = jax.vmap(loaded.dynamics.constraint)(jax.numpy.asarray(x, dtype=jax.numpy.float32))
    np.testing.assert_allclose(loaded_values[:, 1], values, rtol=1e-5, atol=1e-6)
    # by default the keypoints are the bead and the arm's end: the arm turns and carries no hinge, so
    # it gets a point of its own, as from_mjcf gives it (rotation about +y by q carries (0, 0, c) to
    # (c sin q, c cos q); the bead at c = s - 0.4 along the arm, its end at c = -0.8, the pivot at z 1)
    q, s = 0.7, 0.15
    default = keyvision.render_poses(
        BEAD_SCENE.replace('<site name="tip" pos="0 0 -0.8"/>', ""), [[q, s]], image_size=16
    )
    expected = [(s - 0.4) * np.sin(q), 1 + (s - 0.4) * np.cos(q), -0.8 * np.sin(q), 1 - 0.8 * np.cos(q)]
    np.testing.assert_allclose(default["keypoints"], [expected], atol=EXACT)
    # the bead alone cannot carry the arm's turn: refused, naming from_mjcf's keypoints
    alone = dataclasses.replace(
        frames,
        info={**frames.info, "keypoint_names": ["slide"]},
        extras={**frames.extras, "keypoints": frames.extras["keypoints"][..., :2]},
    )
    with pytest.raises(ValueError, match="on the keypoints slide, tip .* the frames have slide"):
        keyvision.scene_constraint(alone)


def test_keypoints_follow_the_joints_in_closed_form(marker_frames):
    """Rotation about +y by q carries (0, 0, L) to (L sin q, 0, L cos q); the plane is world (x, z)."""
    slide, angle = marker_frames.extras["qpos"][..., 0], marker_frames.extras["qpos"][..., 1]
    expected = np.stack([slide + ARM * np.sin(angle), PIVOT_HEIGHT + ARM * np.cos(angle)], axis=-1)
    np.testing.assert_allclose(marker_frames.extras["keypoints"], expected, atol=EXACT)
    np.testing.assert_allclose(marker_frames.camera.basis, [[1, 0, 0], [0, 0, 1]], atol=EXACT)


def test_camera_map_projects_the_rendered_marker(marker_frames):
    """The centroid of the rendered sphere lies where the camera map sends its centre."""
    size = SMALL.image_size
    expected = marker_frames.camera.to_image(marker_frames.extras["keypoints"])  # (R, T, 2)
    light = marker_frames.frames.astype(float).mean(axis=-1)  # (R, T, H, W), black background
    rows, cols = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    weight = light.sum(axis=(-2, -1))
    assert np.all(weight > 0)
    centroid = np.stack([(light * rows).sum((-2, -1)) / weight, (light * cols).sum((-2, -1)) / weight], -1)
    expected_pixels = np.asarray(keyvision.frame_to_pixel(expected, size, size))
    np.testing.assert_allclose(centroid, expected_pixels, atol=PIXEL_TOL)
    homography = marker_frames.camera.homography
    assert abs(homography[2, 0]) + abs(homography[2, 1]) > 1e-3  # the oblique view is not affine


def test_rendering_does_not_depend_on_the_number_of_workers(marker_frames):
    again = keyvision.render(
        MARKER_SCENE, camera="oblique", protocol=SMALL, keypoints=["marker"], cache=False, workers=2
    )
    np.testing.assert_array_equal(again.frames, marker_frames.frames)
    np.testing.assert_array_equal(again.extras["qpos"], marker_frames.extras["qpos"])
    np.testing.assert_array_equal(again.u, marker_frames.u)


def test_one_worker_renders_in_the_calling_process(monkeypatch):
    # so a script without `if __name__ == "__main__":` renders with workers=1 (a spawned worker
    # imports the script again, which renders again); no process pool may be started
    def no_pool(*args, **kwargs):
        raise AssertionError("keyvision.render started a process pool for workers=1")

    monkeypatch.setattr(render_module.concurrent.futures, "ProcessPoolExecutor", no_pool)
    protocol = keyvision.RenderProtocol(runs=2, frames=3, validation_runs=1)
    frames = keyvision.render("keycld/pendulum", protocol=protocol, cache=False, workers=1)
    assert frames.frames.shape == (2, 3, 64, 64, 3) and frames.frames.std() > 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the EGL default is Linux's")
def test_rendering_in_the_calling_process_needs_no_gl_setting():
    # MuJoCo picks its GL backend when first imported; keyvision asks for EGL (headless) unless the
    # environment names one, so rendering in this process works where MUJOCO_GL was never set
    code = (
        "import numpy as np, keyvision\n"
        "protocol = keyvision.RenderProtocol(runs=1, frames=2, validation_runs=0)\n"
        "frames = keyvision.render('keycld/pendulum', protocol=protocol, cache=False, workers=1)\n"
        "poses = keyvision.render_poses('keycld/pendulum', np.zeros((1, 1)))\n"
        "print(frames.frames.std() > 0, poses['frames'].std() > 0)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["True", "True"]


def test_a_process_that_cannot_render_is_told_how_to(monkeypatch):
    def no_context(setup):
        raise RuntimeError("no OpenGL context")

    monkeypatch.setattr(render_module, "_open", no_context)
    protocol = keyvision.RenderProtocol(runs=1, frames=2, validation_runs=0)
    with pytest.raises(RuntimeError, match=r"workers=1\): MuJoCo cannot render in this process .*MUJOCO_GL"):
        keyvision.render("keycld/pendulum", protocol=protocol, cache=False, workers=1)


def test_render_poses_draws_the_poses_with_their_potential_energy(marker_frames):
    """The frames and keypoints of `render` for the same joint positions, and MuJoCo's potential
    energy in closed form: V = g (m_c h + m_a (h + L cos q)), the carriage at the pivot's height."""
    qpos = marker_frames.extras["qpos"].reshape(-1, 2)
    poses = keyvision.render_poses(
        MARKER_SCENE, qpos, camera="oblique", image_size=SMALL.image_size, keypoints=["marker"]
    )
    np.testing.assert_array_equal(poses["frames"], marker_frames.frames.reshape(poses["frames"].shape))
    keypoints = marker_frames.extras["keypoints"].reshape(-1, 2)
    np.testing.assert_allclose(poses["keypoints"], keypoints, atol=EXACT)
    gravity, carriage, arm = 9.81, 1.0, 0.5
    expected = gravity * (carriage * PIVOT_HEIGHT + arm * (PIVOT_HEIGHT + ARM * np.cos(qpos[:, 1])))
    np.testing.assert_allclose(poses["potential"], expected, atol=EXACT)
    with pytest.raises(ValueError, match=r"qpos must be \(N, 2\)"):
        keyvision.render_poses(MARKER_SCENE, qpos[:, :1], camera="oblique")
    with pytest.raises(ValueError, match="NaN"):
        keyvision.render_poses(MARKER_SCENE, np.full((1, 2), np.nan), camera="oblique")


def test_a_supersampled_camera_averages_each_pixels_samples(marker_frames):
    """With `supersample=4` a pixel is the mean of the 4 x 4 pixels of MuJoCo's render at four times
    the size, rounded: the 16-pixel frames are the 64-pixel frames averaged in blocks (a camera's pixel
    integrates light over its area), and the marker's light is the same in both."""
    qpos = marker_frames.extras["qpos"].reshape(-1, 2)
    options = {"camera": "oblique", "keypoints": ["marker"]}
    small = keyvision.render_poses(MARKER_SCENE, qpos, image_size=16, supersample=4, **options)["frames"]
    large = marker_frames.frames.reshape(-1, 64, 64, 3).astype(float)
    blocks = large.reshape(-1, 16, 4, 16, 4, 3).mean(axis=(2, 4))
    assert small.dtype == np.uint8 and small.shape == (len(qpos), 16, 16, 3)
    np.testing.assert_array_equal(small, np.round(blocks))
    assert np.all(large.sum(axis=(1, 2, 3)) > 100)  # the marker is in every frame
    light, rounding = large.sum(axis=(1, 2, 3)) / 16, 16 * 16 * 3 / 2  # half a level per pixel value
    np.testing.assert_allclose(small.sum(axis=(1, 2, 3)), light, atol=rounding)
    with pytest.raises(ValueError, match="supersample"):
        keyvision.RenderProtocol(supersample=0)
    # at its default the field is left out of the request, so caches written before it keep their keys
    assert "supersample" not in marker_frames.info["protocol"]


def test_keycld_pendulum_follows_the_papers_protocol():
    """A.6: dt 0.02 s with (semi-implicit) Euler, one step per frame; the pivot at the image centre;
    one constant control per run in U(-2, 2), zero in 20% of runs; velocities U(-0.1, 0.1)."""
    protocol = keyvision.RenderProtocol(runs=10, frames=3, validation_runs=2)
    frames = keyvision.render("keycld/pendulum", protocol=protocol, cache=False, workers=1)
    assert frames.frames.shape == (10, 3, 64, 64, 3)
    assert frames.dt == 0.02 and frames.info["integrator"] == "EULER"
    qpos, qvel = frames.extras["qpos"][..., 0], frames.extras["qvel"][..., 0]
    np.testing.assert_allclose(qpos[:, 1:] - qpos[:, :-1], 0.02 * qvel[:, 1:], atol=EXACT)
    assert np.all(np.abs(qvel[:, 0]) <= 0.1) and np.all(np.abs(qpos[:, 0]) <= np.pi)
    tip = np.stack([0.5 * np.sin(qpos), 0.6 + 0.5 * np.cos(qpos)], axis=-1)  # pole 0.5 m, pivot z 0.6
    np.testing.assert_allclose(frames.extras["keypoints"], tip, atol=EXACT)
    np.testing.assert_allclose(frames.camera.to_plane(np.zeros(2)), [0.0, 0.6], atol=EXACT)
    controls = frames.u[..., 0]
    assert np.all(controls == controls[:, :1]) and np.all(np.abs(controls) <= 2)
    assert np.sum(controls[:, 0] == 0) == 2
    train, validation = frames.split()
    assert (train.num_runs, validation.num_runs) == (8, 2)
    # the scene's constraints read through the camera are KeyCLD's (the paper's figure 7)
    assert keyvision.scene_constraint(frames) == cldyn.keycld_constraint("pendulum")


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["cartpole", "acrobot"])
def test_keycld_rk4_scenes_and_their_keypoints(scene):
    protocol = keyvision.RenderProtocol(runs=3, frames=3, validation_runs=0)
    frames = keyvision.render(f"keycld/{scene}", protocol=protocol, cache=False, workers=1)
    assert frames.dt == 0.01 and frames.info["integrator"] == "RK4"
    first, second = frames.extras["keypoints"][..., :2], frames.extras["keypoints"][..., 2:]
    if scene == "cartpole":  # the cart on its rail at z = 1, the pole 1 m long
        np.testing.assert_allclose(first[..., 1], 1.0, atol=EXACT)
        anchor = first
    else:  # the elbow 1 m from the shoulder at z = 2.1, the tip 1 m from the elbow
        anchor = np.array([0.0, 2.1])
        np.testing.assert_allclose(np.linalg.norm(first - anchor, axis=-1), 1.0, atol=EXACT)
        anchor = first
    np.testing.assert_allclose(np.linalg.norm(second - anchor, axis=-1), 1.0, atol=EXACT)
    assert len(frames.info["keypoint_names"]) == 2
    assert keyvision.scene_constraint(frames) == cldyn.keycld_constraint(scene)


# -- the cache, without rendering -------------------------------------------------------------------


def _fake_frames(setup, seed, workers, progress_meter):
    runs, count = setup["protocol"].runs, setup["protocol"].frames
    rng = np.random.default_rng(seed)
    return keyvision.Frames(
        frames=rng.integers(0, 256, (runs, count, 8, 8, 3), dtype=np.uint8),
        u=np.zeros((runs, count, 2)),
        dt=0.01,
        extras={"qpos": rng.normal(size=(runs, count, 2))},
        camera=keyvision.PlanarCamera(np.eye(3), np.eye(3)[[0, 2]]),
        info={"validation_runs": 1},
    )


def _refuse_to_render(*args):
    raise AssertionError("rendered again instead of loading the cache")


def test_cache_is_reused_and_keyed_by_the_request(tmp_path, monkeypatch):
    monkeypatch.setattr(render_module, "_render", _fake_frames)
    first = keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)
    (path,) = tmp_path.glob("*.npz")
    monkeypatch.setattr(render_module, "_render", _refuse_to_render)
    again = keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)
    np.testing.assert_array_equal(again.frames, first.frames)
    assert again.info["cache_key"] == first.info["cache_key"]
    monkeypatch.setattr(render_module, "_render", _fake_frames)
    changes = (
        {"seed": 4},
        {"protocol": dataclasses.replace(SMALL, frames=5)},
        {"protocol": dataclasses.replace(SMALL, supersample=2)},
        {"camera": "follow"},
    )
    for change in changes:
        keyvision.render(MARKER_SCENE, **{"protocol": SMALL, "seed": 3, **change}, cache=tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 5


def test_mismatched_cache_is_refused_naming_the_file(tmp_path, monkeypatch):
    monkeypatch.setattr(render_module, "_render", _fake_frames)
    keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)
    (path,) = tmp_path.glob("*.npz")
    other = keyvision.render(MARKER_SCENE, protocol=SMALL, seed=4, cache=False)
    other.save(path)  # another request's frames under this request's name
    monkeypatch.setattr(render_module, "_render", _refuse_to_render)
    with pytest.raises(ValueError, match="another request") as error:
        keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)
    assert str(path) in str(error.value)


def test_truncated_cache_is_refused_naming_the_file(tmp_path, monkeypatch):
    monkeypatch.setattr(render_module, "_render", _fake_frames)
    keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)
    (path,) = tmp_path.glob("*.npz")
    path.write_bytes(path.read_bytes()[:-100])
    monkeypatch.setattr(render_module, "_render", _refuse_to_render)
    with pytest.raises(ValueError, match="delete the file") as error:
        keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)
    assert str(path) in str(error.value)


def test_cache_with_keypoints_other_than_the_scenes_defaults_is_refused(tmp_path, monkeypatch):
    # frames cached before the default keypoints changed: refused naming both lists, not served stale
    def stale(setup, seed, workers, progress_meter):
        frames = _fake_frames(setup, seed, workers, progress_meter)
        return dataclasses.replace(frames, info={**frames.info, "keypoint_names": ["slide"]})

    monkeypatch.setattr(render_module, "_render", stale)
    keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)
    monkeypatch.setattr(render_module, "_render", _refuse_to_render)
    with pytest.raises(ValueError, match=r"keypoints \['slide'\].*now \['slide', 'marker'\]"):
        keyvision.render(MARKER_SCENE, protocol=SMALL, seed=3, cache=tmp_path)


def test_cache_directory_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("KEYVISION_CACHE", str(tmp_path / "cache"))
    assert keyvision.cache_directory() == tmp_path / "cache"
    monkeypatch.setattr(render_module, "_render", _fake_frames)
    keyvision.render(MARKER_SCENE, protocol=SMALL, cache=True)
    assert len(os.listdir(tmp_path / "cache")) == 1


def test_bad_cameras_and_sites_are_refused():
    with pytest.raises(ValueError, match="no camera 'missing'"):
        keyvision.render(MARKER_SCENE, camera="missing", protocol=SMALL, cache=False)
    with pytest.raises(ValueError, match="fixed in the world"):
        keyvision.render(MARKER_SCENE, camera="follow", protocol=SMALL, cache=False)
    with pytest.raises(ValueError, match="no site 'tip'"):
        keyvision.render(MARKER_SCENE, camera="oblique", keypoints=["tip"], protocol=SMALL, cache=False)
    with pytest.raises(ValueError, match="validation_runs"):
        keyvision.RenderProtocol(runs=3, validation_runs=4)
