"""`from_mjcf` against MuJoCo itself: accelerations, joint maps and whole trajectories.

Every expected number here comes from MuJoCo (its keypoint kinematics `J qacc + Jdot qvel`, its RK4
integration), never from the code under test. Float64 throughout (conftest).
"""

import xml.etree.ElementTree as ET

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

import cldyn  # noqa: E402
from cldyn.mujoco import from_mjcf, keycld_scene, record, validate  # noqa: E402
from cldyn.mujoco._scenes import load_model  # noqa: E402

pytestmark = pytest.mark.mujoco

ACCEL_RTOL = 1e-9  # cldyn's xdd against MuJoCo's, relative to the largest component
MAP_ATOL = 1e-12  # the joint maps against MuJoCo's keypoints (m, m/s)
TRAJECTORY_ATOL = 1e-6  # keypoint positions over 2 s (m): the acceptance bound

# Unequal links; the third link's centre of mass is off its axis, with a rotated inertia frame; the
# second hinge axis points the other way and has a `ref`.
TRIPLE = """
<mujoco model="triple">
  <option timestep="0.001" integrator="RK4"><flag contact="disable"/></option>
  <worldbody>
    <body name="link1" pos="0.1 0.3 1.5">
      <joint name="j1" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.9" size="0.04" mass="1.3"/>
      <body name="link2" pos="0 0 -0.9">
        <joint name="j2" type="hinge" axis="0 -1 0" ref="0.4"/>
        <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.03" mass="0.6"/>
        <body name="link3" pos="0.5 0 0">
          <joint name="j3" type="hinge" axis="0 1 0"/>
          <inertial pos="0.25 0.02 0.12" quat="0.9 0.1 0.3 0.2" mass="0.8" diaginertia="0.02 0.015 0.009"/>
          <geom type="capsule" fromto="0 0 0 0.7 0 0" size="0.02" mass="0"/>
          <site name="tip" pos="0.7 0 0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="m1" joint="j1" gear="3"/>
    <motor name="m3" joint="j3" gear="0.5"/>
  </actuator>
</mujoco>
"""

# A slide along a swinging arm (its axis tilted), a hinge at its end, a welded weight; every passive
# effect that `include` can add.
TELESCOPE = """
<mujoco model="telescope">
  <option><flag contact="disable"/></option>
  <worldbody>
    <body name="arm" pos="0 0 1">
      <joint name="swing" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.6" size="0.03" mass="0.7"/>
      <body name="slider" pos="0 0 -0.6">
        <joint name="extend" type="slide" axis="0.3 0 -1" stiffness="20" springref="0.1" damping="0.3"/>
        <geom type="box" size="0.05 0.05 0.05" mass="0.4" pos="0.02 0 0"/>
        <body name="pend" pos="0 0 -0.1">
          <joint name="tilt" type="hinge" axis="0 1 0" armature="0.05" stiffness="0.5" springref="0.2"/>
          <geom type="capsule" fromto="0 0 0 0.3 0 -0.3" size="0.02" mass="0.3"/>
          <body name="weight" pos="0.3 0 -0.3">
            <geom type="sphere" size="0.05" mass="0.2"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="extend" gear="2"/>
    <motor name="twist" joint="tilt"/>
  </actuator>
</mujoco>
"""

# A gantry: a cart on a rail, a lift sliding diagonally on it, and a branching tree below.
GANTRY = """
<mujoco model="gantry">
  <option><flag contact="disable"/></option>
  <worldbody>
    <body name="cart" pos="0 0 1">
      <joint name="x" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.2 0.1 0.05" mass="2"/>
      <body name="lift" pos="0.1 0 -0.1">
        <joint name="z" type="slide" axis="0.6 0 0.8"/>
        <geom type="box" size="0.05 0.05 0.05" mass="0.5"/>
        <body name="left">
          <joint name="a" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="0.3"/>
        </body>
        <body name="right" pos="0.1 0 0">
          <joint name="b" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 -0.4" size="0.02" mass="0.2"/>
          <body name="right2" pos="0.2 0 -0.4">
            <joint name="c" type="hinge" axis="0 1 0"/>
            <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" mass="0.1"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="fx" joint="x"/>
    <motor name="fz" joint="z"/>
    <motor name="tb" joint="b"/>
  </actuator>
</mujoco>
"""

# A double pendulum in a tilted plane (hinge axes along (1, 1, 0) / sqrt 2).
TILTED = """
<mujoco model="tilted">
  <option><flag contact="disable"/></option>
  <worldbody>
    <body name="upper" pos="0 0 2" euler="0 0 45">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/>
      <site name="mid_upper" pos="0.05 0 -0.6"/>
      <body name="lower" pos="0 0 -1">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.8" size="0.04" mass="0.5"/>
        <site name="mid_lower" pos="0 0 -0.4"/>
        <site name="tip" pos="0 0 -0.8"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor name="elbow" joint="elbow"/></actuator>
</mujoco>
"""

# name -> (mjcf, keypoints, include)
CASES = {
    "keycld-pendulum": ("keycld/pendulum", None, ()),
    "keycld-cartpole": ("keycld/cartpole", None, ()),
    "keycld-acrobot": ("keycld/acrobot", None, ()),
    "triple": (TRIPLE, None, ()),
    "pendulum-damped": ("pendulum", None, ("damping",)),
    "cartpole-damped": ("cartpole", None, ("damping",)),
    "acrobot-damped": ("acrobot", None, ("damping",)),
    "telescope": (TELESCOPE, None, ("damping", "stiffness", "armature")),
    "gantry": (GANTRY, None, ()),
    "tilted": (TILTED, None, ()),
    "tilted-sites": (TILTED, ("mid_upper", "tip", "mid_lower"), ()),
}


def _mujoco_states(mjcf, keypoints, *, seed=0, runs=6):
    """Random states (fast motion), random controls, and MuJoCo's keypoint kinematics there."""
    rng = np.random.default_rng(seed)
    start = record(mjcf, runs=runs, duration=0.0, keypoints=keypoints, seed=seed)
    qvel = rng.normal(size=start.extras["qvel"][:, 0].shape) * 2.0
    data = record(
        mjcf,
        duration=0.02,
        dt=0.01,
        keypoints=keypoints,
        seed=seed,
        initial=(start.extras["qpos"][:, 0], qvel),
        control=rng.uniform(-1, 1, (runs, start.u.shape[-1])),
    )
    arrays = {"xd": data.xd, "xdd": data.xdd, "u": data.u}
    arrays.update({name: data.extras[name] for name in ("x_clean", "qpos", "qvel")})
    flat = {name: jnp.asarray(np.reshape(a, (-1, a.shape[-1]))) for name, a in arrays.items()}
    return data, flat


@pytest.mark.parametrize("case", sorted(CASES))
def test_acceleration_matches_mujoco(case):
    mjcf, keypoints, include = CASES[case]
    bridge = from_mjcf(mjcf, keypoints=keypoints, include=include)
    data, s = _mujoco_states(mjcf, keypoints)
    assert bridge.keypoint_names == tuple(data.info["keypoint_names"])
    assert not np.any(data.extras["qfrc_constraint"])  # no limit or contact acted

    xdd = jax.jit(jax.vmap(bridge.system.acceleration))(s["x_clean"], s["xd"], s["u"])
    error = float(jnp.max(jnp.abs(xdd - s["xdd"])) / jnp.max(jnp.abs(s["xdd"])))
    assert error < ACCEL_RTOL, f"{case}: relative acceleration error {error:.2e}"


@pytest.mark.parametrize("case", sorted(CASES))
def test_joint_maps_match_mujoco(case):
    mjcf, keypoints, include = CASES[case]
    bridge = from_mjcf(mjcf, keypoints=keypoints, include=include)
    _, s = _mujoco_states(mjcf, keypoints, seed=1)
    x, xd = jax.jit(jax.vmap(bridge.joints.to_keypoints))(s["qpos"], s["qvel"])
    assert float(jnp.max(jnp.abs(x - s["x_clean"]))) < MAP_ATOL
    assert float(jnp.max(jnp.abs(xd - s["xd"]))) < MAP_ATOL
    qpos, qvel = jax.jit(jax.vmap(bridge.joints.to_joints))(s["x_clean"], s["xd"])
    hinge = load_model(mjcf)[0].jnt_type == mujoco.mjtJoint.mjJNT_HINGE
    difference = np.array(qpos - s["qpos"])
    difference[:, hinge] = np.asarray(cldyn.wrap_angle(difference[:, hinge]))  # angles modulo 2 pi
    assert np.max(np.abs(difference)) < MAP_ATOL
    assert float(jnp.max(jnp.abs(qvel - s["qvel"]))) < MAP_ATOL


def test_names_and_conventions():
    bridge = from_mjcf("keycld/cartpole")
    # KeyCLD's two keypoints: the cart (the slider and the hinge anchor merged) and the pole's end
    assert bridge.keypoint_names == ("slider+hinge_1", "pole_1_end")
    assert bridge.joint_names == ("slider", "hinge_1")
    assert bridge.actuator_names == ("slide", "hinge_1")
    assert bridge.actuator_joints == ("slider", "hinge_1")
    np.testing.assert_allclose(bridge.basis, [[1, 0, 0], [0, 0, 1]])  # world (x, z) -> planar (x, y)
    assert isinstance(bridge.coordinate("slider"), cldyn.SliderPosition)
    assert isinstance(bridge.coordinate("hinge_1"), cldyn.HingeAngle)
    constraints = bridge.system.constraint.constraints
    assert [type(c) for c in constraints] == [cldyn.FixedCoordinate, cldyn.Distance]
    acrobot = from_mjcf("keycld/acrobot")
    assert acrobot.keypoint_names == ("elbow", "tip")
    assert [type(c) for c in acrobot.system.constraint.constraints] == [cldyn.Anchor, cldyn.Distance]
    np.testing.assert_allclose(acrobot.system.constraint.constraints[0].point, [0.0, 2.1])
    assert acrobot.system.potential.g == pytest.approx(9.81)
    assert from_mjcf("keycld/pendulum").keypoint_names == ("pole_end",)


def test_nominal_model_leaves_damping_out():
    """Without `include` the stock acrobot's joint damping is missing: the accelerations differ."""
    nominal = from_mjcf("acrobot")
    damped = from_mjcf("acrobot", include=["damping"])
    assert nominal.system.dissipation is None and damped.system.dissipation is not None
    _, s = _mujoco_states("acrobot", None)
    xdd = jax.jit(jax.vmap(nominal.system.acceleration))(s["x_clean"], s["xd"], s["u"])
    assert float(jnp.max(jnp.abs(xdd - s["xdd"])) / jnp.max(jnp.abs(s["xdd"]))) > 1e-3


ERRORS = {
    "ball joint": (
        '<body pos="0 0 1"><joint name="wrist" type="ball"/><geom size=".1" pos="0 0 -1"/></body>',
        "joint 'wrist' is a ball joint",
    ),
    "free joint": (
        '<body name="puck"><freejoint name="float"/><geom size=".1"/></body>',
        "'float' is a free",
    ),
    "non-parallel hinges": (
        '<body pos="0 0 1"><joint name="h1" axis="0 1 0"/><geom size=".1" pos="0 0 -1"/>'
        '<body pos="0 0 -1"><joint name="h2" axis="1 0 0"/><geom size=".1" pos="0 0 -1"/></body></body>',
        "hinge 'h2' has axis .* not parallel to hinge 'h1'",
    ),
    "slide out of plane": (
        '<body pos="0 0 1"><joint name="h" axis="0 1 0"/><geom size=".1" pos="0 0 -1"/>'
        '<body><joint name="s" type="slide" axis="0 1 0"/><geom size=".1" pos="0 0 -1"/></body></body>',
        "slide 's' has axis .* leaves the plane",
    ),
    "two joints in a body": (
        '<body pos="0 0 1"><joint name="sx" type="slide" axis="1 0 0"/><joint name="h" axis="0 1 0"/>'
        '<geom size=".1" pos="0 0 -1"/></body>',
        "body 'body1' has 2 joints",
    ),
    "contact between moving bodies": (
        '<body pos="0 0 1"><joint axis="0 1 0"/><geom name="g1" size=".1" pos="0 0 -1"/>'
        '<body pos="0 0 -1"><joint axis="0 1 0"/><geom size=".1" pos="0 0 -1"/>'
        '<body pos="0 0 -1"><joint axis="0 1 0"/><geom name="g3" size=".1" pos="0 0 -1"/>'
        "</body></body></body>",
        "geoms 'g1' and 'g3' .* can collide",
    ),
}


@pytest.mark.parametrize("case", sorted(ERRORS))
def test_outside_the_class_names_the_element(case):
    body, message = ERRORS[case]
    xml = f"<mujoco><worldbody>{body}</worldbody></mujoco>"
    with pytest.raises(ValueError, match=message):
        from_mjcf(xml)


def test_more_errors():
    hinge = '<body name="b" pos="0 0 1"><joint name="h" axis="0 1 0"/><geom size=".1" pos="0 0 -1"/></body>'
    with pytest.raises(ValueError, match="tendon 't'"):
        from_mjcf(
            f'<mujoco><worldbody>{hinge}</worldbody><tendon><fixed name="t"><joint joint="h" coef="1"/>'
            "</fixed></tendon></mujoco>"
        )
    with pytest.raises(ValueError, match="equality constraint 'lock'"):
        from_mjcf(
            f'<mujoco><worldbody>{hinge}</worldbody><equality><joint name="lock" joint1="h"/>'
            "</equality></mujoco>"
        )
    for element, message in (
        ('<position name="servo" joint="h" kp="1"/>', r"actuator 'servo' is a servo \(<position>"),
        (
            '<intvelocity name="servo" joint="h" kp="1" actrange="-1 1"/>',
            "actuator 'servo' is an <intvelocity>",
        ),
        (
            '<general name="servo" joint="h" dyntype="filter" dynprm="0.1"/>',
            "actuator 'servo' is an actuator with activation dynamics",
        ),
    ):
        with pytest.raises(ValueError, match=message):
            from_mjcf(f"<mujoco><worldbody>{hinge}</worldbody><actuator>{element}</actuator></mujoco>")
    with pytest.raises(ValueError, match="unknown effect 'friction'; allowed: damping, stiffness, armature"):
        from_mjcf("keycld/pendulum", include=["friction"])
    with pytest.raises(ValueError, match="frictionloss is dry friction"):
        from_mjcf("keycld/pendulum", include=["frictionloss"])
    with pytest.raises(ValueError, match="no site named 'nose'"):
        from_mjcf("acrobot", keypoints=["nose"])
    with pytest.raises(FileNotFoundError, match="MJCF file not found: missing.xml"):
        from_mjcf("missing.xml")
    # the lower link would carry no keypoint
    with pytest.raises(ValueError, match="body 'lower' turns about hinge 'elbow' but carries no keypoint"):
        from_mjcf(TILTED, keypoints=["mid_upper"])
    friction = hinge.replace('axis="0 1 0"', 'axis="0 1 0" frictionloss="0.1"')
    with pytest.warns(UserWarning, match="frictionloss"):
        from_mjcf(f"<mujoco><worldbody>{friction}</worldbody></mujoco>")


def test_massless_keypoint_is_refused():
    """The lower link's mass sits at the elbow and it has no inertia: its tip carries nothing."""
    xml = """
    <mujoco><worldbody><body pos="0 0 1"><joint axis="0 1 0"/><geom size=".1" pos="0 0 -1" mass="1"/>
      <body pos="0 0 -1"><joint axis="0 1 0"/>
        <inertial pos="0 0 0" mass="1" diaginertia="1e-14 1e-14 1e-14"/>
        <site name="tip" pos="0 0 -1"/></body></body></worldbody></mujoco>
    """
    with pytest.raises(ValueError, match="keypoint 'tip' carries no mass"):
        from_mjcf(xml)


VALIDATION = {
    "keycld/pendulum": (),
    "keycld/cartpole": (),
    "keycld/acrobot": (),
    "triple": (),
    "pendulum": ("damping",),
    "cartpole": ("damping",),
    "acrobot": ("damping",),
}


@pytest.mark.parametrize("name", list(VALIDATION))
def test_trajectories_match_mujoco(name, tmp_path):
    """The acceptance test: 10 random initial states and constant controls, 2 s, MuJoCo RK4 at 1e-4."""
    mjcf = TRIPLE if name == "triple" else name
    report = validate(mjcf, out=tmp_path, include=VALIDATION[name], runs=10, duration=2.0, physics_dt=1e-4)
    assert report["runs"] == 10 and report["duration"] == 2.0
    assert not report["mujoco_constraints_active"]
    assert report["max_position_error"] < TRAJECTORY_ATOL, report
    assert (tmp_path / "validation.json").is_file() and (tmp_path / "keypoint_error.png").is_file()


def test_nominal_trajectories_drift_from_damped_mujoco():
    report = validate("acrobot", runs=2, duration=1.0, physics_dt=1e-3)
    assert report["max_position_error"] > 1e-3


def test_mass_equals_the_rigid_body_blocks():
    """For the acrobot the frame construction gives cldyn's pivot and two-keypoint rigid-body blocks."""
    bridge = from_mjcf("keycld/acrobot")
    model = load_model("keycld/acrobot")[0]
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    basis = np.asarray(bridge.basis)

    def body(name):
        b = model.body(name).id
        rotation = data.ximat[b].reshape(3, 3)
        inertia = (rotation.T @ [0, 1, 0]) @ (model.body_inertia[b] * (rotation.T @ [0, 1, 0]))
        return model.body_mass[b], inertia, basis @ data.xipos[b]

    shoulder, elbow, tip = (basis @ p for p in (data.xanchor[0], data.xanchor[1], data.site("tip").xpos))
    upper, lower = body("upper_arm"), body("lower_arm")
    expected = cldyn.ConstantMass.from_blocks(
        [
            ((0,), cldyn.pivot_body_mass(*upper, pivot=shoulder, point=elbow)),
            ((0, 1), cldyn.rigid_body_mass(*lower, points=np.stack([elbow, tip]))),
        ],
        num_keypoints=2,
    )
    np.testing.assert_allclose(bridge.system.mass.matrix(), expected.matrix(), rtol=1e-12, atol=1e-14)


# -- one compilation per structure ------------------------------------------------------------------


def _traced_step():
    """An `eqx.filter_jit` function of a bridge that counts its traces, and a MuJoCo reference."""
    traces = []

    @eqx.filter_jit
    def step(bridge, q, qd, u):
        traces.append(None)
        x, xd = bridge.joints.to_keypoints(q, qd)
        xdd = bridge.system.acceleration(x, xd, u)
        # joint accelerations: the time derivative of qd(x, xd) along (xd, xdd)
        qdd = jax.jvp(lambda y, v: bridge.joints.to_joints(y, v)[1], (x, xd), (xd, xdd))[1]
        return qdd

    return step, traces


def _mujoco_qacc(xml, q, qd, u):
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = q, qd, u
    mujoco.mj_forward(model, data)
    return np.array(data.qacc)


def _resized_acrobot() -> str:
    """The KeyCLD acrobot with other link lengths and masses: the same structure, other numbers."""
    root = ET.fromstring(keycld_scene("acrobot"))
    root.find(".//geom[@name='upper_arm']").set("fromto", "0 0 0 0 0 0.8")
    root.find(".//body[@name='lower_arm']").set("pos", "0 0 0.8")
    lower = root.find(".//geom[@name='lower_arm']")
    lower.set("fromto", "0 0 0 0 0 1.3")
    lower.set("mass", "1.7")
    root.find(".//site[@name='tip']").set("pos", "0 0 1.3")
    return ET.tostring(root, encoding="unicode")


def test_same_scene_built_twice_compiles_once():
    first, second = from_mjcf("keycld/acrobot"), from_mjcf("keycld/acrobot")
    assert first is not second  # two builds, no cache
    assert jax.tree_util.tree_structure(first) == jax.tree_util.tree_structure(second)
    step, traces = _traced_step()
    q, qd, u = jnp.array([0.3, -1.1]), jnp.array([0.7, 0.2]), jnp.array([0.4, -0.3])
    a, b = step(first, q, qd, u), step(second, q, qd, u)
    assert len(traces) == 1
    np.testing.assert_array_equal(a, b)


def test_scenes_differing_in_numbers_share_one_compilation():
    """Other lengths and masses reuse the program, and the program uses the new numbers: the joint
    accelerations agree with MuJoCo's for each scene."""
    resized = _resized_acrobot()
    step, traces = _traced_step()
    q, qd, u = jnp.array([0.3, -1.1]), jnp.array([0.7, 0.2]), jnp.array([0.4, -0.3])
    results = {}
    for xml in (keycld_scene("acrobot"), resized):
        results[xml] = np.asarray(step(from_mjcf(xml), q, qd, u))
        expected = _mujoco_qacc(xml, q, qd, u)
        assert np.max(np.abs(results[xml] - expected)) < ACCEL_RTOL * np.max(np.abs(expected))
    assert len(traces) == 1
    assert np.max(np.abs(results[resized] - results[keycld_scene("acrobot")])) > 0.1


def test_training_moves_the_springs_not_the_joint_conventions():
    """A spring's rest and stiffness take gradients; the offsets by which the frame coordinates of a slide
    on a turning body and a hinge below it match MuJoCo's qpos (geometry, as HingeAngle's are static)
    take none, with cldyn.fit's default of training every array."""
    from cldyn.mujoco._frames import FrameAngle, FrameSlide

    bridge = from_mjcf(TELESCOPE, include=("damping", "stiffness", "armature"))
    x, _ = bridge.joints.to_keypoints(jnp.array([0.4, 0.05, -0.3]), jnp.zeros(3))
    grads = eqx.filter_grad(lambda system: system.potential(x))(bridge.system)
    leaves = jax.tree_util.tree_leaves_with_path(grads)
    frames = [p for p, _ in leaves if any(getattr(k, "name", "") == "offset" for k in p)]
    assert frames  # the frame coordinates are there, and their offsets are arrays
    for path, g in leaves:
        names = [getattr(k, "name", "") for k in path]
        if names[-1] == "offset":
            assert np.all(np.asarray(g) == 0), path
    rests = [g for p, g in leaves if getattr(p[-1], "name", "") == "rest"]
    assert len(rests) == 2 and all(abs(float(g)) > 1e-6 for g in rests)
    kinds = {type(c) for c in bridge.joint_coordinates}
    assert FrameSlide in kinds or FrameAngle in kinds
