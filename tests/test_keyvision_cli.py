"""The `keyvision` command line, in-process through `main(argv)`: bad options and expected failures give
one `keyvision <command>: error: ...` line and status 2 and create nothing; a tiny render -> train ->
evaluate does its job and writes its files."""

import json
import os
import pathlib

import jax
import numpy as np
import pytest

import cldyn
from keyvision._cli import main

COMMANDS = ("render", "train", "distil", "evaluate", "control", "identify")
VPT_TOL = 1e-12  # a fraction of frames, recomputed from the recorded errors

# command -> (arguments with one invalid value, the option the error must name)
BAD_ARGUMENTS = {
    "render": (["--scene", "keycld/pendulum", "--out", "{tmp}/r", "--runs", "0"], "--runs"),
    "train": (["--data", "{tmp}/d", "--out", "{tmp}/t", "--width", "-8"], "--width"),
    "distil": (["--model", "{tmp}/m", "--data", "{tmp}/d", "--out", "{tmp}/o", "--steps", "0"], "--steps"),
    "evaluate": (["--model", "{tmp}/m", "--data", "{tmp}/d", "--out", "{tmp}/e", "--batch", "x"], "--batch"),
    "control": (["--model", "{tmp}/m", "--out", "{tmp}/c", "--runs", "0"], "--runs"),
    "identify": (["--model", "{tmp}/m", "--data", "{tmp}/d", "--out", "{tmp}/i", "--effects", "x"],
                 "--effects"),
}


def _run(capsys, argv):
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def _error_line(err: str, command: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith(f"keyvision {command}: error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_help_lists_every_command(capsys):
    status, out, _ = _run(capsys, ["--help"])
    assert status == 0
    for command in COMMANDS:
        assert command in out
        status, out_command, _ = _run(capsys, [command, "--help"])
        assert status == 0 and "--out" in out_command and "(default:" in out_command


@pytest.mark.parametrize("command", COMMANDS)
def test_a_bad_argument_is_one_error_line_and_creates_nothing(command, tmp_path, capsys):
    arguments, option = BAD_ARGUMENTS[command]
    status, _, err = _run(capsys, [command, *(a.format(tmp=tmp_path) for a in arguments)])
    assert status == 2
    assert option in _error_line(err, command)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["render", "--scene", "keycld/pendulum", "--runs", "2", "--validation-runs", "3"],
            "--validation-runs 3",
        ),
        (["train", "--data", "{tmp}/missing.npz"], "no such file"),
        (["train", "--data", "{tmp}/missing.npz", "--resume", "--overwrite"], "give one"),
        (["evaluate", "--model", "{tmp}/missing", "--data", "{tmp}/missing.npz"], "no such directory"),
        (["control", "--model", "{tmp}/missing"], "no such directory"),
        (["distil", "--model", "{tmp}/missing", "--data", "{tmp}/missing.npz"], "no such file"),
        (["identify", "--model", "{tmp}/missing", "--data", "{tmp}/missing.npz"], "no such file"),
    ],
)
def test_failures_before_any_work_create_nothing(argv, message, tmp_path, capsys):
    status, _, err = _run(capsys, [a.format(tmp=tmp_path) for a in argv] + ["--out", tmp_path / "out"])
    assert status == 2
    assert message in _error_line(err, argv[0])
    assert list(tmp_path.iterdir()) == []


def test_existing_frames_are_refused_without_overwrite(tmp_path, capsys):
    (tmp_path / "frames.npz").write_text("an earlier run's frames")
    argv = ["render", "--scene", "keycld/pendulum", "--out", tmp_path]
    status, _, err = _run(capsys, argv)
    assert status == 2
    assert "pass --overwrite" in _error_line(err, "render")
    assert (tmp_path / "frames.npz").read_text() == "an earlier run's frames"


def _fake_frames(path, scene="keycld/pendulum"):
    """A frames file as `keyvision render` writes it, without MuJoCo: 2 runs of 6 blank frames."""
    import keyvision

    frames = keyvision.Frames(
        frames=np.zeros((2, 6, 16, 16, 3), np.uint8),
        u=np.zeros((2, 6, 1)),
        dt=0.02,
        extras={},
        camera=keyvision.PlanarCamera(np.eye(3), np.eye(2, 3)),
        info={"scene": scene, "keypoint_names": ["tip"], "validation_runs": 1},
    )
    return frames.save(path)


def test_evaluate_names_both_scenes_when_the_frames_do_not_fit_the_model(tmp_path, capsys):
    # the shipped pendulum model (64 x 64 frames, one control) on frames of another scene and size:
    # the error names what does not fit and both scenes, and writes nothing
    shipped = pathlib.Path(__file__).resolve().parents[1] / "keyvision" / "demo" / "pendulum"
    data = _fake_frames(tmp_path / "frames.npz", scene="keycld/cartpole")
    status, _, err = _run(capsys, ["evaluate", "--model", shipped, "--data", data, "--out", tmp_path / "out"])
    line = _error_line(err, "evaluate")
    assert status == 2 and "pixels; the model takes 64 x 64" in line
    assert "(frames of keycld/cartpole; the model was trained on keycld/pendulum)" in line
    assert not (tmp_path / "out").exists()
    # frames of the model's own scene: no scenes named
    data = _fake_frames(tmp_path / "same.npz")
    status, _, err = _run(capsys, ["evaluate", "--model", shipped, "--data", data, "--out", tmp_path / "out"])
    assert status == 2 and "pixels; the model takes 64 x 64" in err and "trained on" not in err


def test_train_needs_constraints_for_a_scene_not_of_keycld(tmp_path, capsys):
    data = _fake_frames(tmp_path / "frames.npz", scene="arm.xml")
    status, _, err = _run(capsys, ["train", "--data", data, "--out", tmp_path / "out"])
    assert status == 2
    assert "--constraint" in _error_line(err, "train")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("option", ["--rigid-steps", "--candidates"])
def test_the_rigid_stage_and_the_candidates_need_constraints(option, tmp_path, capsys):
    data = _fake_frames(tmp_path / "frames.npz")
    status, _, err = _run(capsys, ["train", "--data", data, "--out", tmp_path / "out", "--model", "nc",
                                   option, 5])
    assert status == 2
    assert f"{option}: --model nc has no constraints" in _error_line(err, "train")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("checkpointed", [False, True])
def test_ctrl_c_in_train_says_how_to_resume(checkpointed, tmp_path, capsys, monkeypatch):
    import keyvision

    data, out = _fake_frames(tmp_path / "frames.npz"), tmp_path / "out"

    def interrupted(model, data, *, out, **options):
        if checkpointed:
            (out / "checkpoint-autoencoder.eqx").write_bytes(b"")
        raise KeyboardInterrupt

    monkeypatch.setattr(keyvision, "train", interrupted)
    status, _, err = _run(
        capsys, ["train", "--data", data, "--out", out, "--width", 4, "--window", 5, "--no-progress"]
    )
    assert status == 130
    assert "Traceback" not in err
    if checkpointed:
        assert "keyvision train: interrupted; continue with:" in err and "--resume" in err
        assert (out / "keyvision.json").is_file()
    else:
        assert "nothing to resume" in err
        assert not out.exists()  # left as it was


@pytest.mark.mujoco
@pytest.mark.slow
def test_render_train_evaluate(tmp_path, capsys):
    pytest.importorskip("mujoco")
    imageio = pytest.importorskip("imageio.v3")
    pytest.importorskip("matplotlib")
    import keyvision

    data, model, results, cache = (tmp_path / name for name in ("data", "model", "results", "cache"))
    render = ["render", "--scene", "keycld/pendulum", "--out", data, "--runs", 4, "--frames", 6, "--size", 16]
    render += ["--validation-runs", 1, "--workers", 1, "--cache", cache, "--no-progress"]
    status, out, err = _run(capsys, render)
    assert status == 0, err
    assert "4 runs x 6 frames of 16x16 pixels" in out and "cached in" in out
    frames = keyvision.Frames.load(data / "frames.npz")
    assert frames.frames.shape == (4, 6, 16, 16, 3)
    # the same request again: the cache answers, and --overwrite replaces the frames file
    status, out, err = _run(capsys, render + ["--overwrite"])
    assert status == 0, err
    assert "loaded from the cache" in out
    np.testing.assert_array_equal(keyvision.Frames.load(data / "frames.npz").frames, frames.frames)

    # the joint stage is covered by the library's tests; its compilation would double this test's time
    train = ["train", "--data", data, "--out", model, "--width", 4, "--dynamics-width", 8]
    train += ["--autoencoder-steps", 2, "--dynamics-steps", 2, "--joint-steps", 0, "--refit-steps", 0]
    train += ["--candidates", 2, "--candidate-steps", 2, "--candidate-runs", 2, "--no-progress"]
    status, out, err = _run(capsys, train)
    assert status == 0, err
    summary = json.loads(out)
    assert summary["autoencoder"]["steps"] == 2 and summary["dynamics"]["steps"] == 2
    # two initialisations tried, stage (a) continued the one of the lower constraint score
    scores = [summary["candidates"][f"candidate-{k}"] for k in (1, 2)]
    assert summary["candidates"]["chosen"] == f"candidate-{1 + int(np.argmin(scores))}"
    assert summary["candidates"]["runs"] == 2  # of the 3 training runs, every 2nd
    assert summary["candidate-1"]["steps"] == summary["candidate-2"]["steps"] == 2
    spec = json.loads((model / "keyvision.json").read_text())
    assert spec["keypoints"] == 1 and spec["dynamics"]["constraint"] == "pendulum"
    assert (model / "model.eqx").is_file()
    # the frames' path, relative to the model's directory: it names no machine's directories
    assert not os.path.isabs(spec["data"]["file"])
    assert (model / spec["data"]["file"]).resolve() == (data / "frames.npz").resolve()
    status, _, err = _run(capsys, train)
    assert status == 2 and "--resume" in _error_line(err, "train")
    status, _, err = _run(capsys, train + ["--resume", "--lr", 0.01])
    line = _error_line(err, "train")  # names the option that differs, with both values, and no other
    assert status == 2 and "options differ" in line and "(schedule.learning_rate 0.001 -> 0.01)" in line
    # a training recorded with an absolute path to its frames (as before paths were relative) resumes
    spec["data"]["file"] = str((data / "frames.npz").resolve())
    (model / "keyvision.json").write_text(json.dumps(spec))
    # more rounds extend a finished training (here rounds without steps: nothing more to run) ...
    status, out, err = _run(capsys, train + ["--resume", "--rounds", 3])
    assert status == 0, err
    spec = json.loads((model / "keyvision.json").read_text())
    assert spec["schedule"]["rounds"] == 3 and not os.path.isabs(spec["data"]["file"])
    # ... and fewer would drop finished rounds: refused
    status, _, err = _run(capsys, train + ["--resume", "--rounds", 2])
    assert status == 2 and "(schedule.rounds 3 -> 2)" in _error_line(err, "train")

    # an ablation of the dynamics starting from this training's autoencoder: stage (a) is not run again
    import jax

    shared = tmp_path / "shared"
    ablation = ["train", "--data", data, "--out", shared, "--width", 4, "--dynamics-width", 8]
    ablation += ["--model", "nc", "--dynamics-steps", 2, "--joint-steps", 0, "--refit-steps", 0]
    ablation += ["--no-progress"]
    status, _, err = _run(capsys, ablation + ["--networks-from", model])
    assert status == 0, err
    assert not (shared / "history-autoencoder.json").exists()
    spec = json.loads((shared / "keyvision.json").read_text())
    assert spec["schedule"]["autoencoder_steps"] == 0 and spec["networks_from"]["autoencoder_seconds"] > 0
    assert (shared / spec["networks_from"]["directory"]).resolve() == model.resolve()
    autoencoder, _ = keyvision.load_model(model, stage="autoencoder")
    trained_nc, _ = keyvision.load_model(shared)
    for part in ("estimator", "renderer"):  # no stage here trained the networks
        pairs = zip(jax.tree.leaves(getattr(trained_nc, part)), jax.tree.leaves(getattr(autoencoder, part)))
        for a, b in pairs:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert spec["schedule"]["dynamics_learning_rate"] == 0.001  # the networks' rate by default
    # the structured dynamics (no networks) from the same autoencoder, its stages at their own rate
    # (by default 1e-2 for this kind)
    structured = ablation[:4] + [tmp_path / "structured"] + ablation[5:]
    structured[structured.index("nc")] = "keycld-structured"
    status, _, err = _run(capsys, structured + ["--networks-from", model])
    assert status == 0, err
    trained_structured, spec = keyvision.load_model(tmp_path / "structured")
    assert spec["dynamics"]["kind"] == "keycld-structured"
    assert spec["schedule"]["dynamics_learning_rate"] == 0.01
    assert isinstance(trained_structured.dynamics.potential, cldyn.Gravity)
    assert trained_structured.dynamics.input_matrix.coordinates == cldyn.keycld_joints("pendulum")
    status, _, err = _run(capsys, ablation[:-1] + ["--overwrite", "--width", 8, "--networks-from", model])
    assert status == 2 and "--networks-from" in _error_line(err, "train") and "width" in err

    status, out, err = _run(capsys, ["evaluate", "--model", model, "--data", data, "--out", results])
    assert status == 0, err
    assert out.startswith("VPT over 1 validation runs of 6 frames")
    record = json.loads((results / "vpt.json").read_text())
    (vpt,) = record["vpt_per_run"]
    # the VPT is the first frame whose error exceeds the threshold, as a fraction of the 6 frames
    exceeded = np.asarray(record["mse_over_time"]) > record["threshold"]
    expected = np.argmax(exceeded) / 6 if exceeded.any() else 1.0
    assert vpt == pytest.approx(expected, abs=VPT_TOL)
    assert record["vpt"]["mean"] == pytest.approx(vpt, abs=VPT_TOL)
    assert record["failed_runs"] == []
    # the strip shows the true validation frames (every one of the 6) over the predicted ones
    strip = imageio.imread(results / "strip.png")
    assert strip.shape == (32, 6 * 16, 3)
    truth = np.concatenate(list(frames.frames[-1]), axis=1)
    np.testing.assert_array_equal(strip[:16], truth)
    assert os.path.getsize(results / "mse.png") > 0
    # the GIF: every frame, true (with the estimated keypoint) beside predicted, four times enlarged
    movie = imageio.imread(results / "prediction.gif", index=None)
    assert movie.shape[:3] == (6, 4 * 16, 2 * 4 * 16)
    assert np.isfinite(record["keypoint_tracking_r2"]) and record["keypoint_tracking_r2"] <= 1
    assert all(np.isfinite(e) and e >= 0 for e in record["keypoint_error_px"])
    # the model after stage (b), rebuilt from the stages' files: here the finished model itself
    status, out, err = _run(capsys, ["evaluate", "--model", model, "--stage", "dynamics", "--data", data,
                                     "--out", tmp_path / "stage"])
    assert status == 0, err
    staged = json.loads((tmp_path / "stage" / "vpt.json").read_text())
    assert staged["stage"] == "dynamics" and staged["vpt_per_run"] == record["vpt_per_run"]
    status, _, err = _run(capsys, ["evaluate", "--model", model, "--stage", "joint-2", "--data", data,
                                   "--out", tmp_path / "none"])
    assert status == 2 and "no stage 'joint-2'" in _error_line(err, "evaluate")
    # identify: the whole path on the tiny model, on runs long enough to be smoothed (18 frames)
    measured = tmp_path / "measured"
    longer = render[:4] + [measured, "--runs", 5, "--frames", 20, "--size", 16, "--validation-runs", 1]
    status, _, err = _run(capsys, longer + ["--workers", 1, "--no-cache", "--no-progress"])
    assert status == 0, err
    # with a few steps of the model's joint stage on the identified runs, after the effects are added
    # (one call: identify's path is the same with or without them, and it is most of this test's time)
    identify = ["identify", "--model", model, "--data", measured, "--out", tmp_path / "id", "--no-progress"]
    status, out, err = _run(capsys, identify + ["--refine-steps", 2, "--add-balance"])
    assert status == 0, err
    found = json.loads((tmp_path / "id" / "effects.json").read_text())
    assert found["joints"] == {"hinge": "hinge"} and found["outcome"] in out
    assert (tmp_path / "id" / "report.md").is_file()
    # the energy balance beside the detections: the hinge's missing damping, in N m s and in model units
    (balance,) = found["energy_balance"]
    assert balance["where"] == "hinge" and balance["ci"][0] <= balance["value"] <= balance["ci"][1]
    assert balance["value"] / balance["value_model"] == pytest.approx(found["joules_per_unit"], rel=1e-6)
    assert "energy balance" in out
    # --add-balance: the balance's damping is an effect of the model exactly where its interval lies
    # above zero, the force residual found no damping and the held-out rollout test did not leave it out
    # (the report's warnings name what it left out)
    residual = [e for e in found["effects"] if e["source"] == "force residual"]
    damped = {e["where"] for e in residual if e["name"] == "joint_damping"}
    added = [(e["where"], e["value_model"]) for e in found["effects"] if e["source"] == "energy balance"]
    warnings = json.loads((tmp_path / "id" / "report.json").read_text())["warnings"]
    refused = [w for w in warnings if "energy balance" in w and "not added" in w]
    left_out = {b["where"] for b in found["energy_balance"] if any(f"[{b['where']}]" in w for w in refused)}
    expected = [
        b for b in found["energy_balance"] if b["detected"] and b["where"] not in damped | left_out
    ]
    assert added == [(b["where"], b["value_model"]) for b in expected]
    assert found["images"]["runs"] == 1 and 0 <= found["images"]["before"]["vpt"]["mean"] <= 1
    # the image error frame by frame: its mean is the MSE over all frames; plotted in image_error.png
    for name in ("before", "after"):
        per_frame = found["images"][name]["mse_over_time"]
        assert len(per_frame) == 20 and np.mean(per_frame) == pytest.approx(found["images"][name]["mse"])
        assert found["images"][name]["failed_runs"] == []  # every prediction ran to its end
    assert (tmp_path / "id" / "image_error.png").stat().st_size > 0
    # the refined model, scored beside
    refined = found["images"]["refined"]
    assert 0 <= refined["vpt"]["mean"] <= 1 and np.isfinite(refined["mse"])
    assert "refined with the image losses" in out
    # the camera's scale: the width of the image frame (2 units) seen at the pendulum's plane
    edges = frames.camera.to_plane(np.array([[-1.0, 0.0], [1.0, 0.0]]))
    assert found["metres_per_unit"] == pytest.approx(np.linalg.norm(edges[1] - edges[0]) / 2, rel=1e-3)
    # the constraint drift: the pendulum's one constraint is the keypoint's distance from the image
    # centre (Anchor(0)); its standard deviation along the validation run, in pixels of 16
    trained, _ = keyvision.load_model(model)
    keypoints = np.asarray(trained.encode(frames.frames[-1].astype(np.float32) / 255), dtype=float)
    expected = np.std(np.linalg.norm(keypoints, axis=-1)) * 16 / 2
    (drift,) = record["constraint_drift_px"]
    assert drift == pytest.approx(expected, rel=1e-3, abs=1e-6)


# A chain of three links hanging from a pivot that the camera does not centre (the image centre is
# 0.25 m to its right and 0.4 m below it), one motor at the pivot: not one of KeyCLD's scenes.
CHAIN_LINKS = (0.5, 0.4, 0.3)
CHAIN_PIVOT = (0.0, 1.6)
CHAIN_SCENE = f"""
<mujoco model="chain">
  <option timestep="0.01" integrator="RK4"><flag contact="disable"/></option>
  <worldbody>
    <light pos="0 -1 4" dir="0 0 -1"/>
    <camera name="fixed" pos="0.25 -4 1.2" zaxis="0 -1 0"/>
    <body name="link1" pos="{CHAIN_PIVOT[0]} 0 {CHAIN_PIVOT[1]}">
      <joint name="pivot" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -{CHAIN_LINKS[0]}" size="0.04" mass="1" rgba="1 0 0 1"/>
      <body name="link2" pos="0 0 -{CHAIN_LINKS[0]}">
        <joint name="knee" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -{CHAIN_LINKS[1]}" size="0.04" mass="0.8" rgba="0 1 0 1"/>
        <body name="link3" pos="0 0 -{CHAIN_LINKS[1]}">
          <joint name="ankle" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0 0 -{CHAIN_LINKS[2]}" size="0.04" mass="0.5" rgba="0 0 1 1"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="pivot" gear="1"/></actuator>
</mujoco>
"""


@pytest.mark.mujoco
def test_render_takes_the_keypoints_at_named_sites(tmp_path, capsys):
    # --keypoints reaches keyvision.render: a site the scene lacks is refused by name, before rendering
    pytest.importorskip("mujoco")
    xml = tmp_path / "chain.xml"
    xml.write_text(CHAIN_SCENE)
    render = ["render", "--scene", xml, "--out", tmp_path / "data", "--keypoints", "nose", "--no-cache"]
    status, _, err = _run(capsys, render)
    line = _error_line(err, "render")
    assert status == 2 and "no site 'nose'" in line and not (tmp_path / "data" / "frames.npz").exists()


@pytest.mark.mujoco
def test_train_reads_the_constraints_of_a_scene_that_is_not_keyclds(tmp_path, capsys):
    # the chain's pivot, seen off the image centre, and its two rods: read from the MJCF through the
    # camera, checked against the scene's geometry in closed form
    pytest.importorskip("mujoco")
    import keyvision

    xml, data, model = tmp_path / "chain.xml", tmp_path / "data", tmp_path / "model"
    xml.write_text(CHAIN_SCENE)
    render = ["render", "--scene", xml, "--out", data, "--runs", 3, "--frames", 6, "--size", 16]
    render += ["--validation-runs", 1, "--workers", 1, "--no-cache", "--no-progress"]
    status, _, err = _run(capsys, render)
    assert status == 0, err
    frames = keyvision.Frames.load(data / "frames.npz")
    # MuJoCo's camera (fovy 45 degrees) 4 m from the plane, centred on (0.25, 1.2): the image frame's
    # unit is 4 tan(22.5 degrees) metres, and the pivot is seen at (-0.25, 0.4) m from the centre
    metres_per_unit = 4 * np.tan(np.radians(22.5))
    pivot = (np.array(CHAIN_PIVOT) - [0.25, 1.2]) / metres_per_unit
    constraint = keyvision.scene_constraint(frames)
    assert constraint.constraints[1:] == (cldyn.Distance(0, 1), cldyn.Distance(1, 2))
    assert isinstance(constraint.constraints[0], cldyn.Anchor) and constraint.constraints[0].keypoint == 0
    np.testing.assert_allclose(constraint.constraints[0].point, pivot, atol=1e-9)
    # along the runs, the true keypoints seen in the image keep the links' lengths in image units
    seen = frames.camera.to_image(frames.extras["keypoints"].reshape(-1, 3, 2)).reshape(-1, 6)
    values = np.asarray(jax.vmap(constraint)(jax.numpy.asarray(seen)))
    lengths = np.array(CHAIN_LINKS) / metres_per_unit
    np.testing.assert_allclose(values, np.broadcast_to(lengths, values.shape), rtol=1e-6)

    train = ["train", "--data", data, "--out", model, "--width", 4, "--dynamics-width", 8, "--candidates", 1]
    train += ["--autoencoder-steps", 1, "--dynamics-steps", 1, "--joint-steps", 0, "--refit-steps", 0]
    status, _, err = _run(capsys, train + ["--no-progress"])
    assert status == 0, err
    spec = json.loads((model / "keyvision.json").read_text())
    assert spec["dynamics"]["constraint"][1:] == [{"distance": [0, 1]}, {"distance": [1, 2]}]
    np.testing.assert_allclose(spec["dynamics"]["constraint"][0]["point"], pivot, atol=1e-9)
    trained, _ = keyvision.load_model(model)
    assert trained.dynamics.constraint == constraint
    # the structured kind's joints are KeyCLD's scenes': refused, naming the way out
    status, _, err = _run(capsys, train + ["--model", "keycld-structured", "--overwrite"])
    line = _error_line(err, "train")
    assert status == 2 and "keycld-structured" in line and "--model keycld" in line


@pytest.mark.mujoco
def test_demo_predicts_new_runs_with_the_shipped_model(tmp_path, capsys):
    # the shipped pendulum model on two runs it never saw: its estimator tracks the pole (an affine map
    # of the keypoint explains the true pose), frames redrawn from their own keypoints stay under the
    # VPT threshold for the whole run, and the learnt dynamics predict well past the first frames
    status, out, err = _run(capsys, ["demo", "--out", tmp_path, "--runs", "2", "--seed", "7"])
    assert status == 0, err
    record = json.loads((tmp_path / "vpt.json").read_text())
    assert record["runs"] == 2 and record["frames"] == 50
    assert record["keypoint_tracking_r2"] > 0.95
    # the pole's keypoint follows a point of the pole to about a pixel (an affine fit to MuJoCo's tip)
    assert len(record["keypoint_error_px"]) == 1 and 0 < record["keypoint_error_px"][0] < 1.5
    # ... and moves with it: its distances from its mean position are those of the true tip's, scaled by
    # where along the pole the estimator put it (0.36: about a third of the way from the pivot)
    assert len(record["keypoint_motion"]) == 1 and 0.2 < record["keypoint_motion"][0] < 1.1
    assert record["autoencoder"]["vpt"]["mean"] > 0.9
    assert record["autoencoder"]["mse_over_threshold"] < 0.5
    assert record["vpt"]["mean"] > 0.2
    for name in ("frames.npz", "mse.png", "strip.png", "prediction.gif"):
        assert (tmp_path / name).stat().st_size > 0
    assert "autoencoder alone" in out


def test_a_stage_that_diverged_says_what_is_kept_and_how_to_go_on(tmp_path):
    from keyvision._cli._train import _diverged

    error = cldyn.NonFiniteLossError(
        "fit: non-finite loss or gradient at step 7 of stage 'refit'", step=7, model=None, checkpoint=None
    )
    assert _diverged(error, tmp_path) == str(error)  # nothing finished: nothing more to say
    for age, stage in enumerate(("autoencoder", "dynamics", "joint-2")):  # in the order written
        (tmp_path / f"model-{stage}.eqx").write_bytes(b"")
        os.utime(tmp_path / f"model-{stage}.eqx", ns=(10**9 * (age + 1),) * 2)
    said = _diverged(error, tmp_path)
    assert said.startswith(str(error))
    assert f"kept in {tmp_path} (autoencoder, dynamics, joint-2)" in said
    assert f"keyvision evaluate --model {tmp_path} --stage joint-2" in said
    assert f"--networks-from {tmp_path}" in said and "(a lower --lr)" in said
    # where the stage failed before any update, its learning rate played no part: not suggested
    first = cldyn.NonFiniteLossError("fit: ...", step=1, model=None, checkpoint=None, before_any_update=True)
    said = _diverged(first, tmp_path)
    assert f"--networks-from {tmp_path}" in said and "--lr" not in said
    (tmp_path / "model-autoencoder.eqx").unlink()  # without an autoencoder stage, no --networks-from
    assert "--networks-from" not in _diverged(error, tmp_path)


def test_keypoint_motion_sees_a_keypoint_that_stands_still():
    """The affine fit of the keypoint error maps any true pose onto a still keypoint exactly; the motion
    ratio does not: the true keypoints scaled by 0.9 about any point move 0.9 as far, a still one 0."""
    import types

    from keyvision._cli._evaluate import _keypoint_error, _keypoint_motion

    rng = np.random.default_rng(0)
    truth = rng.normal(size=(40, 4))  # two keypoints, the camera the identity
    validation = types.SimpleNamespace(
        camera=types.SimpleNamespace(to_image=lambda p: p), extras={"keypoints": truth}, image_size=(16, 16)
    )
    estimated = np.concatenate([0.9 * truth[:, :2] + 0.3, np.full((40, 2), 0.25)], axis=1)
    np.testing.assert_allclose(_keypoint_motion(validation, estimated), [0.9, 0.0], atol=1e-12)
    np.testing.assert_allclose(_keypoint_error(validation, estimated), 0.0, atol=1e-9)  # blind to both
