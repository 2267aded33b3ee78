"""MJCF sources: files, XML strings, dm_control suite names and KeyCLD's scene variants."""

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")
dm_mujoco = pytest.importorskip("dm_control.mujoco")
suite = pytest.importorskip("dm_control.suite")

from cldyn.mujoco import keycld_scene, scene_xml  # noqa: E402
from cldyn.mujoco._scenes import load_model  # noqa: E402

KEYCLD = ("pendulum", "cartpole", "acrobot")


def _compiled(name):
    return mujoco.MjModel.from_xml_string(keycld_scene(name))


def _stock(name):
    xml, assets = getattr(suite, name).get_model_and_assets()
    return mujoco.MjModel.from_xml_string(xml, assets)


def _actuators(model):
    return {model.actuator(a).name: model.actuator(a) for a in range(model.nu)}


@pytest.mark.parametrize("name", KEYCLD)
def test_keycld_scenes_follow_the_paper(name):
    model = _compiled(name)
    stock = _stock(name)
    assert np.all(model.dof_damping == 0)
    assert not np.any(model.actuator_ctrllimited)
    assert model.nu == model.njnt  # every joint actuated
    gears = {n: a.gear[0] for n, a in _actuators(model).items()}
    camera = model.camera("fixed").pos
    if name == "pendulum":
        assert gears == {"torque": 2.0}
        np.testing.assert_allclose(camera, [0, -2.5, 0.6])
        # looking along +y, so the plane of motion faces the camera
        view = model.cam_mat0[model.camera("fixed").id].reshape(3, 3)[:, 2]
        np.testing.assert_allclose(view, [0, -1, 0], atol=1e-12)
    elif name == "cartpole":
        assert gears == {"slide": 4.0, "hinge_1": 1.0}
        assert not model.jnt_limited[model.joint("slider").id]
        np.testing.assert_allclose(camera, [0, -6, 1])
        assert model.geom("pole_1").size[0] == pytest.approx(0.09)
        assert model.geom("floor").pos[2] == pytest.approx(-0.2)
        assert model.geom("rail1").size[1] > stock.geom("rail1").size[1]
        assert model.geom("cart").matid[0] == model.mat("decoration").id
        # the pole keeps its mass
        assert model.body("pole_1").mass[0] == pytest.approx(stock.body("pole_1").mass[0])
    else:
        assert gears == {"shoulder": 2.0, "elbow": 2.0}
        assert list(_actuators(model)) == ["shoulder", "elbow"]
        np.testing.assert_allclose(camera, [0, -6, 2.1])
        assert model.body("upper_arm").pos[2] == pytest.approx(2.1)
        assert model.geom("upper_arm").size[0] == pytest.approx(0.1)
        assert model.geom("lower_arm").size[0] == pytest.approx(0.098)
        assert model.geom("upper_arm").matid[0] == model.mat("decoration").id


@pytest.mark.parametrize("name", KEYCLD)
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
    assert load_model(f"keycld/{name}")[0].nu >= stock.nu


@pytest.mark.parametrize("name", KEYCLD)
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
