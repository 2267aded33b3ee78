"""The joints of a model learnt from images, read from its constraints or from its scene, against
closed-form chains and MuJoCo's qpos; the energy scale that the actuator gears fix, against a model
whose input matrix is known; the unit conversions. (The whole path, frames to report, runs in
tests/test_keyvision_cli.py.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
import keyvision
from keyvision._identify import _convert, _joules_at, energy_scale, metres_per_unit
from keyvision._joints import model_joints

EXACT = 1e-12
SAMPLES = 40
L1, L2, RAIL = 0.4, 0.3, 0.15  # link lengths and the rail's height, keypoint units


def _wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def _acrobot(a, b):
    elbow = np.stack([L1 * np.sin(a), -L1 * np.cos(a)], -1)
    tip = elbow + np.stack([L2 * np.sin(a + b), -L2 * np.cos(a + b)], -1)
    return np.concatenate([elbow, tip], -1)


def _cartpole(c, a):
    cart = np.stack([c, np.full_like(c, RAIL)], -1)
    return np.concatenate([cart, cart + np.stack([L2 * np.sin(a), -L2 * np.cos(a)], -1)], -1)


@pytest.fixture
def angles():
    rng = np.random.default_rng(0)
    return rng.uniform(-3, 3, (2, SAMPLES))


def test_acrobot_joints_are_the_shoulder_and_the_elbow_relative_to_the_first_link(angles):
    """Keypoints of a closed-form double pendulum: the shoulder angle from straight down, the elbow's
    from the first link, the measured lengths, and F(q(x)) = x."""
    a, b = angles
    x = _acrobot(a, b)
    structure = keyvision.joint_structure(cldyn.keycld_constraint("acrobot"), x, ["shoulder", "elbow"])
    assert structure.kinds == ("hinge", "hinge")
    np.testing.assert_allclose(structure.levels, [L1, L2], atol=EXACT)
    q = np.asarray(jax.vmap(structure.joint_map.inverse)(jnp.asarray(x)))
    np.testing.assert_allclose(q, np.stack([_wrap(a), _wrap(b)], -1), atol=1e-9)
    np.testing.assert_allclose(jax.vmap(structure.joint_map.forward)(jnp.asarray(q)), x, atol=1e-12)
    np.testing.assert_allclose(structure.coordinates["elbow"](jnp.asarray(x[0])), _wrap(b[0]), atol=1e-9)


def test_cartpole_joints_are_a_slide_and_a_hinge_from_straight_down(angles):
    c, a = angles[0] / 3, angles[1]
    x = _cartpole(c, a)
    structure = keyvision.joint_structure(cldyn.keycld_constraint("cartpole"), x, ["slider", "hinge_1"])
    assert structure.kinds == ("slide", "hinge")
    np.testing.assert_allclose(structure.levels, [RAIL, L2], atol=EXACT)
    q = np.asarray(jax.vmap(structure.joint_map.inverse)(jnp.asarray(x)))
    np.testing.assert_allclose(q, np.stack([c, _wrap(a)], -1), atol=1e-9)
    np.testing.assert_allclose(jax.vmap(structure.joint_map.forward)(jnp.asarray(q)), x, atol=1e-12)


@pytest.mark.parametrize("incline", [0.4, -2.0])
def test_a_cart_on_an_inclined_rail_slides_along_it(angles, incline):
    # the cart at distance c along a rail through (0.3, RAIL) at `incline` (its normal the one row of a
    # LinearConstraint, of any scale), the pole hinged on it from straight down
    c, a = angles[0] / 3, angles[1]
    along = np.array([np.cos(incline), np.sin(incline)])
    sense = 1.0 if along[0] > 0 else -1.0  # joint_structure measures along the rail rightwards
    cart = np.array([0.3, RAIL]) + (c * sense)[:, None] * along
    x = np.concatenate([cart, cart + np.stack([L2 * np.sin(a), -L2 * np.cos(a)], -1)], -1)
    normal = np.array([-along[1], along[0]])
    rail = cldyn.LinearConstraint([[*(2.5 * normal), 0.0, 0.0]])
    structure = keyvision.joint_structure(cldyn.Stack([rail, cldyn.Distance(0, 1)]), x, ["rail", "hinge"])
    assert structure.kinds == ("slide", "hinge")
    np.testing.assert_allclose(structure.levels, [normal @ [0.3, RAIL], L2], atol=EXACT)
    q = np.asarray(jax.vmap(structure.joint_map.inverse)(jnp.asarray(x)))
    offset = sense * along @ [0.3, RAIL]  # the slide's origin is the rail's foot from the image origin
    np.testing.assert_allclose(q, np.stack([c + offset, _wrap(a)], -1), atol=1e-9)
    np.testing.assert_allclose(jax.vmap(structure.joint_map.forward)(jnp.asarray(q)), x, atol=1e-12)
    # two rows, or a row on two keypoints, are no rail
    for rows in ([[*normal, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]], [[*normal, 1.0, 0.0]]):
        with pytest.raises(ValueError, match="one row on one keypoint"):
            keyvision.joint_structure(cldyn.Stack([cldyn.LinearConstraint(rows), cldyn.Distance(0, 1)]), x)


def test_structures_that_are_not_a_planar_chain_are_refused(angles):
    x = _acrobot(*angles)
    twice = cldyn.Stack([cldyn.Anchor(0), cldyn.Distance(1, 0)])
    with pytest.raises(ValueError, match="keypoint 0 is constrained twice"):
        keyvision.joint_structure(twice, x)
    loop = cldyn.Stack([cldyn.Distance(1, 0), cldyn.Distance(0, 1)])
    with pytest.raises(ValueError, match="loop"):
        keyvision.joint_structure(loop, x)
    with pytest.raises(ValueError, match="3 names for the chain's 2 joints"):
        keyvision.joint_structure(cldyn.keycld_constraint("acrobot"), x, ["a", "b", "c"])
    # an unconstrained keypoint is two slides
    free = keyvision.joint_structure(None, x[:, :2])
    assert free.kinds == ("slide", "slide")
    np.testing.assert_allclose(jax.vmap(free.joint_map.inverse)(jnp.asarray(x[:, :2])), x[:, :2], atol=EXACT)


def test_energy_scale_is_the_gear_over_the_learnt_joint_gain():
    """A cart-pole whose input matrix pushes the cart along x with `b` per unit control: at the slide,
    G^T B = b, so kappa = gear * s / b; a hinge driven through the pole's tip at angle 0 gets L2 b2."""
    b, b2, gear, s = 0.5, 0.25, 4.0, 2.5
    matrix = jnp.array([[b, 0.0], [0.0, 0.0], [0.0, b2], [0.0, 0.0]])
    model = cldyn.ConstrainedLagrangian(
        mass=cldyn.PointMasses(jnp.ones(2)), constraint=cldyn.keycld_constraint("cartpole"),
        input_matrix=cldyn.ConstantInput(matrix),
    )
    x = _cartpole(np.zeros(5), np.zeros(5))  # hanging: the tip moves along x as the pole turns
    structure = keyvision.joint_structure(model.constraint, x, ["slider", "hinge_1"])
    scale = energy_scale(model, structure, x, {"slider": gear, "hinge_1": 1.0}, s)
    assert scale["per_joint"]["slider"] == pytest.approx(gear * s / b, rel=1e-12)
    assert scale["per_joint"]["hinge_1"] == pytest.approx(1.0 / (L2 * b2), rel=1e-12)
    magnitudes = sorted(abs(v) for v in scale["per_joint"].values())
    assert scale["joules_per_unit"] == pytest.approx(np.mean(magnitudes), rel=1e-12)  # median of two
    assert scale["spread"] == pytest.approx(magnitudes[1] / magnitudes[0], rel=1e-12)
    # an effect at an actuated joint converts with that joint's own scale, elsewhere with the median
    assert _joules_at("slider", scale) == pytest.approx(gear * s / b, rel=1e-12)
    assert _joules_at("hinge_1", scale) == pytest.approx(1.0 / (L2 * b2), rel=1e-12)
    assert _joules_at("elbow", scale) == scale["joules_per_unit"]


def test_effects_convert_to_mujoco_units():
    """Damping is force per velocity: joules per unit over (metres per unit)^2 on a slide; on a hinge
    the angle needs no conversion; Coulomb friction is a force; a gain ratio has no unit."""
    kappa, s = 3.0, 2.0
    assert _convert("joint_damping", "slide", 0.5, kappa, s) == pytest.approx(0.5 * kappa / s**2)
    assert _convert("joint_damping", "hinge", 0.5, kappa, s) == pytest.approx(0.5 * kappa)
    assert _convert("joint_coulomb", "slide", 0.5, kappa, s) == pytest.approx(0.5 * kappa / s)
    assert _convert("actuator_gain", "", 1.2, kappa, s) == 1.2
    assert _convert("keypoint_drag", "", 1.2, kappa, s) is None


def test_metres_per_unit_of_a_square_camera():
    """A camera that maps the image frame to the plane by a scale of 1.7 metres per unit."""
    camera = keyvision.PlanarCamera(np.diag([1.7, 1.7, 1.0]), np.array([[1.0, 0, 0], [0, 0, 1.0]]))
    assert metres_per_unit(camera) == pytest.approx(1.7, rel=1e-9)


def test_controls_are_placed_on_the_model_inputs_by_actuator_name():
    """dm_control's stock acrobot drives the elbow only: its control goes to the input the model
    learnt for the elbow, the shoulder's input stays at zero; names that do not match are refused."""
    pytest.importorskip("mujoco")
    from keyvision._identify import _place_controls

    assert keyvision.scene_actuators("keycld/acrobot") == ("shoulder", "elbow")
    assert keyvision.scene_actuators("keycld/acrobot:stock") == ("elbow",)
    rng = np.random.default_rng(0)
    camera = keyvision.PlanarCamera(np.eye(3), np.array([[1.0, 0, 0], [0, 0, 1.0]]))
    frames = keyvision.Frames(
        np.zeros((3, 4, 8, 8, 3), np.uint8), rng.uniform(-1, 1, (3, 4, 1)), 0.01, {}, camera,
        {"actuator_names": ["elbow"]},
    )
    placed = _place_controls(frames, ("shoulder", "elbow"), 2)
    np.testing.assert_array_equal(placed.u[..., 1], frames.u[..., 0])
    np.testing.assert_array_equal(placed.u[..., 0], 0.0)
    assert _place_controls(frames, ("elbow",), 1).u.shape == (3, 4, 1)
    with pytest.raises(ValueError, match="the frames have 1 controls and the model 2 inputs"):
        _place_controls(frames, None, 2)
    with pytest.raises(ValueError, match="actuator 'elbow' drives none of the model's inputs"):
        _place_controls(frames, ("shoulder", "wrist"), 2)
    with pytest.raises(ValueError, match="inputs names 1 actuators; the model has 2 inputs"):
        _place_controls(frames, ("elbow",), 2)


def _reference_runs(damping, *, runs=8, seconds=2.0, dt=0.01, seed=3):
    """The acrobot of tests/helpers.py (its damping a joint-space force written there, not cldyn's
    term), from random rest states, one random constant control per run."""
    from helpers import reference_systems, simulate_reference

    system, _, reference = reference_systems()["acrobot"]
    rng = np.random.default_rng(seed)
    samples = int(round(seconds / dt)) + 1
    q0 = rng.uniform(-2.5, 2.5, size=(runs, 2))
    us = np.repeat(rng.uniform(-1.0, 1.0, size=(runs, 1, system.num_inputs)), samples, axis=1)
    force = lambda q, qd: -jnp.asarray(damping) * qd  # noqa: E731
    run = jax.jit(
        jax.vmap(lambda a, u: simulate_reference(reference, a, jnp.zeros(2), u, dt, samples, force=force)[0])
    )
    return system, cldyn.Sequences(np.asarray(run(jnp.asarray(q0), jnp.asarray(us))), us, dt)


@pytest.mark.slow
def test_the_balances_damping_is_added_only_where_it_lowers_the_held_out_rollout_error():
    """`add_balance`'s test, the one `cldyn.identify` puts to its detections: the true damping passes;
    a damping the runs do not have is named and left out, alone or beside a true one."""
    from keyvision._balance import add_checked_balance

    def entries(**values):
        return [{"where": w, "value": v, "value_model": v, "detected": True} for w, v in values.items()]

    system, elbow_only = _reference_runs((0.0, 0.03))
    structure = keyvision.joint_structure(system.constraint, elbow_only.x[0], ["shoulder", "elbow"])
    held = [0, 1, 2, 3]
    model, added, notes = add_checked_balance(system, entries(elbow=0.03), [], structure, elbow_only, held)
    assert [(a["where"], a["source"]) for a in added] == [("elbow", "energy balance")] and not notes
    assert model.dissipation is not None
    # a false shoulder damping beside the true elbow's: the elbow's is kept, the shoulder's is named
    model, added, notes = add_checked_balance(
        system, entries(shoulder=0.05, elbow=0.03), [], structure, elbow_only, held
    )
    assert [a["where"] for a in added] == ["elbow"], notes
    assert len(notes) == 1 and "joint_damping[shoulder]" in notes[0] and "not added" in notes[0]
    # on damping-free runs, a damping is not added at all
    _, free = _reference_runs((0.0, 0.0))
    model, added, notes = add_checked_balance(system, entries(elbow=0.03), [], structure, free, held)
    assert added == [] and model is system and "joint_damping[elbow]" in notes[0]
    # where the force residual found a damping, the balance's is not added (and nothing is rolled out)
    found = [{"name": "joint_damping", "where": "elbow"}]
    assert add_checked_balance(system, entries(elbow=0.03), found, structure, free, held) == (system, [], [])


# Scenes whose constraints in the image are forms joint_structure does not read: their joints come from
# the scene (keyvision.scene_joints), checked against closed forms and MuJoCo's qpos.
BEAD_ON_ARM = """
<mujoco model="bead">
  <option timestep="0.01" integrator="RK4"><flag contact="disable"/></option>
  <worldbody>
    <light pos="0 -1 4" dir="0 0 -1"/>
    <camera name="fixed" pos="0.2 -4 0.8" zaxis="0 -1 0"/>
    <body name="arm" pos="0 0 1">
      <joint name="swing" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.8" size="0.02" mass="0.5" rgba="0 1 0 1"/>
      <site name="end" pos="0 0 -0.8"/>
      <body name="bead" pos="0 0 -0.4">
        <joint name="along" type="slide" axis="0 0 1"/>
        <geom type="sphere" size="0.06" mass="0.3" rgba="1 0 0 1"/>
        <site name="bead"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="swing"/></actuator>
</mujoco>
"""
# a cart seen by two keypoints at its ends (tied to a body that does not turn), its pole hinged at the
# cart's centre, which is no keypoint
TWO_POINT_CART = """
<mujoco model="two-point-cart">
  <option timestep="0.01" integrator="RK4"><flag contact="disable"/></option>
  <worldbody>
    <light pos="0 -1 4" dir="0 0 -1"/>
    <camera name="fixed" pos="0 -4 1" zaxis="0 -1 0"/>
    <body name="cart" pos="0 0 0.7">
      <joint name="rail" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.2 0.05 0.05" mass="1" rgba="1 0 0 1"/>
      <site name="left" pos="-0.2 0 0"/>
      <site name="right" pos="0.2 0 0"/>
      <body name="pole">
        <joint name="pivot" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.03" mass="0.3" rgba="0 1 0 1"/>
        <site name="top" pos="0 0 0.6"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="rail"/><motor joint="pivot"/></actuator>
</mujoco>
"""


def _scene_frames(xml, keypoints):
    pytest.importorskip("mujoco")
    protocol = keyvision.RenderProtocol(runs=3, frames=6, validation_runs=1, image_size=16, slide_limit=0.2)
    return keyvision.render(xml, protocol=protocol, keypoints=keypoints, cache=False, workers=1)


def _check_scene_joints(frames, structure, closed_form):
    """q(x) is MuJoCo's qpos (slides over the camera's metres per unit), F(q) the closed form seen by the
    camera, and F(q(x)) = x on the frames' true keypoints."""
    metres = metres_per_unit(frames.camera)
    scales = np.where(np.array(structure.kinds) == "slide", metres, 1.0)
    count = frames.extras["keypoints"].shape[-1] // 2
    seen = frames.camera.to_image(frames.extras["keypoints"].reshape(-1, count, 2)).reshape(-1, 2 * count)
    q = np.asarray(jax.vmap(structure.joint_map.inverse)(jnp.asarray(seen)))
    np.testing.assert_allclose(q * scales, frames.extras["qpos"].reshape(-1, len(scales)), atol=1e-9)
    pose = np.random.default_rng(1).uniform(-2, 2, (SAMPLES, len(scales))) * [1, 0.1][: len(scales)]
    expected = frames.camera.to_image(closed_form(*pose.T).reshape(SAMPLES, count, 2)).reshape(SAMPLES, -1)
    forward = np.asarray(jax.vmap(structure.joint_map.forward)(jnp.asarray(pose / scales)))
    np.testing.assert_allclose(forward, expected, atol=1e-9)
    np.testing.assert_allclose(jax.vmap(structure.joint_map.forward)(jnp.asarray(q)), seen, atol=1e-9)


def _check_moved(constraint, partway, x, frames, structure):
    """The joints read on keypoints that keep a distance at their own length (`partway`) are the scene's
    joints of the true keypoints `x`, and the joints' keypoints are `partway` again."""
    read = model_joints(constraint, partway, frames, None).joint_map
    q = np.asarray(jax.vmap(read.inverse)(jnp.asarray(partway)))
    np.testing.assert_allclose(q, jax.vmap(structure.joint_map.inverse)(jnp.asarray(x)), atol=1e-9)
    np.testing.assert_allclose(jax.vmap(read.forward)(jnp.asarray(q)), partway, atol=1e-9)


@pytest.mark.mujoco
def test_a_bead_on_a_swinging_arm_has_the_scenes_hinge_and_slide():
    frames = _scene_frames(BEAD_ON_ARM, ["bead", "end"])
    constraint = keyvision.scene_constraint(frames)  # the pivot, and the bead's slide on the turning arm
    with pytest.raises(ValueError, match="not one of a planar chain"):
        keyvision.joint_structure(constraint, np.zeros(4))
    structure = keyvision.scene_joints(frames)
    assert structure.names == ("swing", "along") and structure.kinds == ("hinge", "slide")
    assert structure.levels == ()

    def closed_form(angle, slide):  # rotation about +y by q carries (0, 0, c) to (c sin q, c cos q)
        bead = np.stack([(slide - 0.4) * np.sin(angle), 1 + (slide - 0.4) * np.cos(angle)], -1)
        return np.concatenate([bead, np.stack([-0.8 * np.sin(angle), 1 - 0.8 * np.cos(angle)], -1)], -1)

    _check_scene_joints(frames, structure, closed_form)
    # keyvision.identify takes the scene's joints for such a model, refusing keypoints of another scene
    x = frames.camera.to_image(frames.extras["keypoints"].reshape(-1, 2, 2)).reshape(-1, 4)
    assert model_joints(constraint, x, frames, None).names == ("swing", "along")
    assert model_joints(cldyn.keycld_constraint("acrobot"), _acrobot(*np.ones((2, 5))), frames, None).levels
    with pytest.raises(ValueError, match="the model has 3 keypoints, its frames' scene 2"):
        model_joints(constraint, np.zeros((5, 6)), frames, None)
    # an arm keypoint that sits partway along the arm keeps the pivot's constraint at its own length:
    # it is moved to the scene's along its ray, so the joints read on it are the scene's, and the joints'
    # keypoints are the model's again
    partway = x.copy()
    pivot = np.asarray(constraint.constraints[0].point)
    partway[:, 2:] = pivot + 0.46 * (x[:, 2:] - pivot)
    _check_moved(constraint, partway, x, frames, structure)
    # and refusing a distance kept near zero: the arm's end drawn onto the pivot, as an estimator did
    collapsed = x.copy()
    collapsed[:, 2:] = np.asarray(constraint.constraints[0].point) + 1e-3 * x[:, 2:]
    with pytest.raises(ValueError, match=r"constraint 0 \(Anchor\) at 0.00\d+ image units, the scene at 0.4"):
        model_joints(constraint, collapsed, frames, None)


@pytest.mark.mujoco
def test_a_cart_seen_at_both_ends_with_a_pole_hinged_between_them():
    frames = _scene_frames(TWO_POINT_CART, ["left", "right", "top"])
    kinds = {type(part).__name__ for part in keyvision.scene_constraint(frames).constraints}
    assert "LinearConstraint" in kinds and "NormConstraint" in kinds  # tied keypoints, an anchor off them
    structure = keyvision.scene_joints(frames)
    assert structure.names == ("rail", "pivot") and structure.kinds == ("slide", "hinge")

    def closed_form(cart, angle):
        height = np.full_like(cart, 0.7)
        ends = [np.stack([cart - 0.2, height], -1), np.stack([cart + 0.2, height], -1)]
        top = np.stack([cart + 0.6 * np.sin(angle), height + 0.6 * np.cos(angle)], -1)
        return np.concatenate([*ends, top], -1)

    _check_scene_joints(frames, structure, closed_form)
    # a pole keypoint 0.4 of the way up the pole keeps the hinge's |d(x)| at its own length, off the
    # scene's by 60%: it is moved along the pole from the cart's centre (the mean of the two ends, no
    # keypoint) to the scene's length, so the joints read on it are the scene's, and back
    constraint = keyvision.scene_constraint(frames)
    x = frames.camera.to_image(frames.extras["keypoints"].reshape(-1, 3, 2)).reshape(-1, 6)
    centre = (x[:, 0:2] + x[:, 2:4]) / 2
    partway = x.copy()
    partway[:, 4:] = centre + 0.4 * (x[:, 4:] - centre)
    _check_moved(constraint, partway, x, frames, structure)
    collapsed = x.copy()
    collapsed[:, 4:] = centre + 1e-3 * (x[:, 4:] - centre)
    said = r"\(NormConstraint\) at 0.000\d+ m of the scene's plane, the scene at 0.6:"
    with pytest.raises(ValueError, match=said):
        model_joints(constraint, collapsed, frames, None)
