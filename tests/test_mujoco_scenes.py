"""MJCF sources, and KeyCLD's scene variants measured against what the paper and its authors' code state.

The KeyCLD checks never re-read the XML edits that build the scenes: they measure the compiled MuJoCo
model or its motion (forces for a given control, energy along a free motion, where the camera sees the
pivot) and compare with the figures of the paper's appendix A.6 and of its authors' fork of
dm_control (`/work/shared/reference/README.md`), or with dm_control's own stock scenes.
"""

import jax.numpy as jnp
import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")
dm_mujoco = pytest.importorskip("dm_control.mujoco")
suite = pytest.importorskip("dm_control.suite")

from cldyn import KEYCLD_SCENES  # noqa: E402
from cldyn.mujoco import from_mjcf, keycld_scene, scene_xml  # noqa: E402
from cldyn.mujoco._scenes import load_model  # noqa: E402

pytestmark = pytest.mark.mujoco

# The reference's figures: the motor gear on each joint (every joint actuated), the fixed camera's
# position, and the number of keypoints of the paper's model (Fig. 7, "the number of keypoints equals
# the number of bodies").
GEARS = {
    "pendulum": {"hinge": 2.0},
    "cartpole": {"slider": 4.0, "hinge_1": 1.0},
    "acrobot": {"shoulder": 2.0, "elbow": 2.0},
}
CAMERAS = {"pendulum": (0.0, -2.5, 0.6), "cartpole": (0.0, -6.0, 1.0), "acrobot": (0.0, -6.0, 2.1)}
KEYPOINTS = {"pendulum": 1, "cartpole": 2, "acrobot": 2}

CONTROL = 50.0  # far beyond every stock control range (|u| <= 1)
ENERGY_RTOL = 1e-8  # total energy over a free motion, MuJoCo RK4 at 1 ms for 2 s
GEOMETRY_ATOL = 1e-9  # camera and keypoint positions (m)
RAIL_PUSH = 3.0  # seconds of a constant push on the cart


def _compiled(name):
    return mujoco.MjModel.from_xml_string(keycld_scene(name))


def _stock(name):
    xml, assets = getattr(suite, name).get_model_and_assets()
    return mujoco.MjModel.from_xml_string(xml, assets)


def _geom_ends(model, data, body):
    """Both ends of every capsule or cylinder of `body` and the centres of its other geoms (world)."""
    points = []
    for g in np.flatnonzero(model.geom_bodyid == body):
        axis = data.geom_xmat[g].reshape(3, 3)[:, 2]
        if model.geom_type[g] in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
            half = model.geom_size[g, 1] * axis
            points += [data.geom_xpos[g] + half, data.geom_xpos[g] - half]
        else:
            points.append(data.geom_xpos[g])
    return points


def _joint_of_actuator(model, a):
    return model.joint(int(model.actuator_trnid[a, 0])).name


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_every_joint_actuated_with_the_reference_gears_and_no_control_limit(name):
    """A large control reaches the joints unclamped, multiplied by the reference's gears."""
    model = _compiled(name)
    data = mujoco.MjData(model)
    assert model.nu == model.nv  # fully actuated
    rng = np.random.default_rng(0)
    data.ctrl[:] = CONTROL * rng.choice([-1.0, 1.0], model.nu)
    mujoco.mj_forward(model, data)
    expected = np.zeros(model.nv)
    for a in range(model.nu):
        joint = _joint_of_actuator(model, a)
        expected[model.joint(joint).dofadr[0]] += GEARS[name][joint] * data.ctrl[a]
    np.testing.assert_allclose(data.qfrc_actuator, expected, rtol=1e-12)
    assert {_joint_of_actuator(model, a) for a in range(model.nu)} == set(GEARS[name])


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_no_friction_the_energy_of_a_free_motion_is_conserved(name):
    """ "Friction was removed": without control, MuJoCo's total energy stays constant (a damping of the
    stock scenes' size would lose orders of magnitude more than the tolerance)."""
    model = _compiled(name)
    model.opt.timestep = 1e-3
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    data = mujoco.MjData(model)
    rng = np.random.default_rng(1)
    data.qpos[:] = rng.uniform(-1.0, 1.0, model.nq)
    data.qvel[:] = rng.uniform(-2.0, 2.0, model.nv)
    mujoco.mj_forward(model, data)
    start = data.energy.sum()
    scale = np.abs(data.energy).sum()
    for _ in range(2000):
        mujoco.mj_step(model, data)
    assert abs(data.energy.sum() - start) < ENERGY_RTOL * scale
    assert not data.nefc  # no limit, contact or friction constraint was active


def test_cartpole_rail_has_no_limit():
    """The slider limit is disabled: a push drives the cart past the stock scene's limit freely."""
    stock = _stock("cartpole")
    slider = stock.joint("slider")
    assert stock.jnt_limited[slider.id]
    model = _compiled("cartpole")
    data = mujoco.MjData(model)
    push = [a for a in range(model.nu) if _joint_of_actuator(model, a) == "slider"]
    data.ctrl[push] = 2.0
    steps = int(round(RAIL_PUSH / model.opt.timestep))
    for _ in range(steps):
        mujoco.mj_step(model, data)
        assert not data.nefc
    assert data.qpos[model.joint("slider").qposadr[0]] > 2 * stock.jnt_range[slider.id, 1]


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_camera_faces_the_plane_with_the_pivot_at_the_image_centre(name):
    model = _compiled(name)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    camera = model.camera("fixed").id
    np.testing.assert_allclose(data.cam_xpos[camera], CAMERAS[name], atol=GEOMETRY_ATOL)
    frame = data.cam_xmat[camera].reshape(3, 3)
    view = -frame[:, 2]  # MuJoCo's cameras look along their -z axis
    hinges = [j for j in range(model.njnt) if model.jnt_type[j] == int(mujoco.mjtJoint.mjJNT_HINGE)]
    for j in hinges:  # the plane of motion is perpendicular to the line of sight
        assert abs(abs(np.dot(view, data.xaxis[j])) - 1.0) < 1e-12
    pivot = data.xanchor[hinges[0]]
    in_camera = frame.T @ (pivot - data.cam_xpos[camera])
    np.testing.assert_allclose(in_camera[:2], 0.0, atol=GEOMETRY_ATOL)  # on the optical axis
    assert in_camera[2] < 0  # in front of the camera


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_the_paper_keypoints_and_constraints(name):
    """Fig. 7: one keypoint per body at the far end (pendulum: the tip; cart-pole: the cart and the
    pole's end; acrobot: the elbow and the tip), with as many constraints as leave the joints' freedom."""
    bridge = from_mjcf(f"keycld/{name}")
    model = _compiled(name)
    assert len(bridge.keypoint_names) == KEYPOINTS[name]
    assert 2 * KEYPOINTS[name] - bridge.system.constraint.num_constraints == model.nv
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    basis = np.asarray(bridge.basis)
    x0 = np.asarray(bridge.joints.keypoints(jnp.asarray(model.qpos0))).reshape(-1, 2)
    anchor = data.xanchor[model.njnt - 1]  # the outermost link's joint
    tip = max(_geom_ends(model, data, model.nbody - 1), key=lambda p: np.linalg.norm(p - anchor))
    np.testing.assert_allclose(x0[-1], basis @ tip, atol=GEOMETRY_ATOL)
    if name != "pendulum":  # the other keypoint sits on the last joint's axis: the cart, the elbow
        np.testing.assert_allclose(x0[0], basis @ anchor, atol=GEOMETRY_ATOL)


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_keycld_scenes_keep_the_stock_masses(name):
    """The changes are of actuation, view and colour: the bodies weigh what dm_control's do."""
    np.testing.assert_array_equal(_compiled(name).body_mass, _stock(name).body_mass)


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_stock_scenes_stay_available(name):
    ours = load_model(name)[0]
    stock = _stock(name)
    for field in (
        "body_mass",
        "body_inertia",
        "dof_damping",
        "actuator_gear",
        "actuator_ctrlrange",
        "jnt_limited",
    ):
        np.testing.assert_array_equal(getattr(ours, field), getattr(stock, field), err_msg=field)


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_stock_physics_under_the_keycld_look(name):
    """`physics="stock"`: dm_control's dynamics, field by field, and the KeyCLD scene's look: the same
    pixels from the same camera in the same poses (so a model trained on KeyCLD's frames can see it)."""
    ours = mujoco.MjModel.from_xml_string(keycld_scene(name, physics="stock"))
    stock = _stock(name)
    for field in (
        "body_mass",
        "body_inertia",
        "body_ipos",
        "dof_damping",
        "dof_armature",
        "dof_frictionloss",
        "actuator_gear",
        "actuator_ctrlrange",
        "actuator_ctrllimited",
        "jnt_limited",
        "jnt_range",
    ):
        np.testing.assert_array_equal(getattr(ours, field), getattr(stock, field), err_msg=field)
    assert keycld_scene(f"keycld/{name}:stock") == keycld_scene(name, physics="stock")
    keycld = _compiled(name)
    cameras = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "fixed") for m in (ours, keycld)]
    np.testing.assert_array_equal(ours.cam_pos[cameras[0]], keycld.cam_pos[cameras[1]])
    poses = np.random.default_rng(0).uniform(-np.pi, np.pi, size=(3, ours.nq))
    images = []
    for model in (ours, keycld):
        data = mujoco.MjData(model)
        with mujoco.Renderer(model, 64, 64) as renderer:
            for q in poses:
                data.qpos[:] = q
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, camera="fixed")
                images.append(renderer.render().copy())
    np.testing.assert_array_equal(np.stack(images[:3]), np.stack(images[3:]))
    assert np.stack(images).std() > 1.0
    with pytest.raises(ValueError, match="physics must be one of keycld, stock, got 'real'"):
        keycld_scene(name, physics="real")


@pytest.mark.parametrize("poles", [2, 3])
def test_the_suite_tasks_with_more_poles_are_scenes(poles):
    """`cartpole/two_poles` is the scene of dm_control's `two_poles` task: the stock cart-pole with a
    chain of poles, its rail limits and its one motor on the cart."""
    name = f"cartpole/{('two', 'three')[poles - 2]}_poles"
    ours = load_model(name)[0]
    stock = suite.load("cartpole", name.split("/")[1]).physics.model.ptr
    for field in ("body_mass", "body_inertia", "dof_damping", "actuator_gear", "jnt_limited", "jnt_range"):
        np.testing.assert_array_equal(getattr(ours, field), getattr(stock, field), err_msg=field)
    bridge = from_mjcf(name)
    assert bridge.joint_names == ("slider",) + tuple(f"hinge_{i}" for i in range(1, poles + 1))
    assert bridge.actuator_names == ("slide",)
    assert bridge.joint_limits[0] == (-1.8, 1.8)


@pytest.mark.parametrize("name", KEYCLD_SCENES)
def test_keycld_scenes_render_with_dm_control(name):
    physics = dm_mujoco.Physics.from_xml_string(keycld_scene(name))
    image = physics.render(64, 64, camera_id="fixed")
    assert image.shape == (64, 64, 3)
    assert image.std() > 1.0  # not a blank frame


def test_sources(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "body.xml").write_text(
        '<mujoco><worldbody><body name="b" pos="0 0 1"><joint name="h" axis="0 1 0"/>'
        '<geom type="sphere" size=".1" pos="0 0 -1"/></body></worldbody></mujoco>'
    )
    main = tmp_path / "scene.xml"
    main.write_text('<mujoco model="m"><include file="parts/body.xml"/></mujoco>')
    text = scene_xml(main)
    assert "<include" not in text and 'name="b"' in text
    from_text = mujoco.MjModel.from_xml_string(text)
    from_path, _, source = load_model(str(main))
    assert source == str(main)
    np.testing.assert_array_equal(from_text.body_mass, from_path.body_mass)
    assert load_model(text)[2] == "<xml string>"


def test_missing_file_and_unknown_names():
    with pytest.raises(FileNotFoundError, match="MJCF file not found: no/such/scene.xml"):
        load_model("no/such/scene.xml")
    with pytest.raises(ValueError, match="unknown scene 'pendulumm'.*suite domain"):
        load_model("pendulumm")
    with pytest.raises(ValueError, match="unknown KeyCLD scene 'keycld/walker'"):
        keycld_scene("keycld/walker")
