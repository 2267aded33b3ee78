"""The `cldyn` command line, in-process through `main(argv)`: help, bad options and expected failures give
one `cldyn <command>: error: ...` line and status 2 (never a traceback), and tiny runs of each command
do their job."""

import importlib
import json
import os
import shlex
import stat
import sys

import equinox as eqx
import jax
import numpy as np
import pytest

import cldyn
from cldyn._cli import _fit as fit_command, _record, main

COMMANDS = ("demo", "record", "validate", "identify", "control", "fit")

# command -> (arguments with one invalid number, the option the error must name)
BAD_NUMBERS = {
    "demo": (["--noise", "nan"], "--noise"),
    "record": (["--mjcf", "keycld/pendulum", "--out", "{tmp}/x.npz", "--runs", "0"], "--runs"),
    "validate": (["--mjcf", "keycld/pendulum", "--out", "{tmp}/v", "--duration", "inf"], "--duration"),
    "identify": (
        ["--data", "d.npz", "--model", "acrobot", "--out", "{tmp}/r", "--holdout", "1"],
        "--holdout",
    ),
    "control": (["--mjcf", "keycld/pendulum", "--out", "{tmp}/c", "--kp", "-1"], "--kp"),
    "fit": (["--scene", "pendulum", "--out", "{tmp}/f", "--lr", "nan"], "--lr"),
}

PENDULUM_TOL = 1e-12  # the pendulum's tip stays on its circle (m): a rigid pole in MuJoCo
VALIDATE_TOL = 1e-6  # from_mjcf against MuJoCo over 0.1 s (m); the full check is in test_mujoco_bridge


def _run(capsys, argv):
    status = main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return status, out, err


def test_help_lists_every_command_and_version(capsys):
    status, out, _ = _run(capsys, [])
    assert status == 0 and all(command in out for command in COMMANDS)
    status, out, _ = _run(capsys, ["--version"])
    assert status == 0 and out.strip() == cldyn.__version__


@pytest.mark.parametrize("command", COMMANDS)
def test_help_shows_the_defaults(command, capsys):
    status, out, _ = _run(capsys, [command, "--help"])
    assert status == 0
    assert out.startswith(f"usage: cldyn {command}")
    assert "(default: " in out and "%%" not in out
    assert "(default: True)" not in out and "(default: False)" not in out  # flags say what they do


@pytest.mark.parametrize("command", COMMANDS)
def test_a_bad_number_is_one_error_line_before_any_work(command, tmp_path, capsys):
    arguments, option = BAD_NUMBERS[command]
    status, _, err = _run(capsys, [command] + [a.format(tmp=tmp_path) for a in arguments])
    assert status == 2
    assert f"cldyn {command}: error: argument {option}: must " in err
    assert not any(tmp_path.iterdir())  # nothing created


def test_unknown_command_and_option(capsys):
    status, _, err = _run(capsys, ["nonsense"])
    assert status == 2 and "cldyn: error: argument <command>: invalid choice: 'nonsense'" in err
    status, _, err = _run(capsys, ["record", "--mjcf", "x", "--out", "y", "--bogus"])
    assert status == 2 and "cldyn record: error: unrecognized arguments: --bogus" in err


def test_an_unusable_output_fails_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    cases = {
        "record": ["--mjcf", "keycld/pendulum", "--out", str(blocker / "x.npz")],
        "validate": ["--mjcf", "keycld/pendulum", "--out", str(blocker / "v")],
        "control": ["--mjcf", "keycld/pendulum", "--out", str(blocker)],
        "identify": ["--data", str(blocker), "--model", "acrobot", "--out", str(blocker / "r")],
        "fit": ["--scene", "pendulum", "--out", str(blocker)],
        "demo": ["--out", str(blocker)],
    }
    for command, arguments in cases.items():
        status, _, err = _run(capsys, [command] + arguments)
        assert status == 2, command
        assert f"cldyn {command}: error: --out {blocker}" in err, err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through permission bits")
def test_a_read_only_output_directory_fails_before_any_work(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        for command, arguments in {
            "record": ["--mjcf", "keycld/pendulum", "--out", str(locked / "x.npz")],
            "validate": ["--mjcf", "keycld/pendulum", "--out", str(locked / "v")],
            "fit": ["--scene", "pendulum", "--out", str(locked)],
        }.items():
            status, _, err = _run(capsys, [command] + arguments)
            assert status == 2 and f"cldyn {command}: error: --out {locked}" in err
            assert "cannot create files in" in err
        assert not any(locked.iterdir())
    finally:
        locked.chmod(stat.S_IRWXU)


# command -> (its arguments with --out in {tmp}, an earlier run's result the command would replace)
EXISTING = {
    "record": (["--mjcf", "keycld/pendulum", "--out", "{tmp}/x"], "x.npz"),
    "validate": (["--mjcf", "keycld/pendulum", "--out", "{tmp}"], "validation.json"),
    "identify": (["--data", "{tmp}/in.npz", "--model", "acrobot", "--out", "{tmp}"], "report.md"),
    "control": (["--mjcf", "keycld/pendulum", "--out", "{tmp}"], "control.png"),
    "demo": (["--out", "{tmp}"], "identify/report.json"),
    "fit": (["--scene", "pendulum", "--out", "{tmp}"], "model.eqx"),
}


@pytest.mark.parametrize("command", sorted(EXISTING))
def test_existing_results_are_refused_without_overwrite(command, tmp_path, capsys):
    arguments, name = EXISTING[command]
    (tmp_path / "in.npz").write_bytes(b"")
    earlier = tmp_path / name
    earlier.parent.mkdir(exist_ok=True)
    earlier.write_bytes(b"an earlier result")
    status, _, err = _run(capsys, [command] + [a.format(tmp=tmp_path) for a in arguments])
    assert status == 2 and f"cldyn {command}: error: --out: " in err
    assert f"{earlier} already exists" in err and "--overwrite" in err
    assert earlier.read_bytes() == b"an earlier result"


def test_contradictory_fit_options(tmp_path, capsys):
    common = ["fit", "--scene", "pendulum", "--out", str(tmp_path / "f")]
    status, _, err = _run(capsys, common + ["--force"])
    assert status == 2 and "cldyn fit: error: --force only applies with --resume" in err
    status, _, err = _run(capsys, common + ["--resume", "--overwrite"])
    assert status == 2 and "cldyn fit: error: --resume continues" in err
    # too few runs for the validation runs and the batch: refused before recording anything
    status, _, err = _run(capsys, common + ["--runs", "10"])
    assert status == 2 and "error: --validation-runs 50: must be fewer than the 10 runs" in err
    status, _, err = _run(capsys, common + ["--runs", "60", "--batch-size", "11"])
    assert status == 2 and "error: --batch-size 11: larger than the 10 training runs" in err
    assert not any(tmp_path.iterdir())


def test_a_missing_input_and_an_unknown_scene_are_one_error_line(tmp_path, capsys):
    arguments = ["--data", str(tmp_path / "missing.npz"), "--model", "acrobot", "--out", str(tmp_path / "r")]
    status, _, err = _run(capsys, ["identify"] + arguments)
    assert status == 2 and "cldyn identify: error: --data" in err and "no such file" in err
    # without the [mujoco] extra the error names the extra instead: one line either way
    status, _, err = _run(capsys, ["validate", "--mjcf", "pendulumm", "--out", str(tmp_path / "v")])
    assert status == 2 and err.startswith("cldyn validate: error: ")
    assert "pendulumm" in err or "cldyn[mujoco]" in err


def test_without_mujoco_the_error_names_the_extra(tmp_path, capsys, monkeypatch):
    for name in [n for n in sys.modules if n == "cldyn.mujoco" or n.startswith("cldyn.mujoco.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "mujoco", None)  # as if it were not installed
    with pytest.raises(
        ImportError, match=r"cldyn.mujoco needs the optional package 'mujoco'.*cldyn\[mujoco\]"
    ):
        importlib.import_module("cldyn.mujoco")
    status, _, err = _run(capsys, ["record", "--mjcf", "keycld/pendulum", "--out", str(tmp_path / "x.npz")])
    assert status == 2 and "cldyn record: error: cldyn.mujoco needs" in err and "cldyn[mujoco]" in err


def test_ctrl_c_exits_130_without_a_traceback(tmp_path, capsys, monkeypatch):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(_record, "run", interrupted)
    status, _, err = _run(capsys, ["record", "--mjcf", "keycld/pendulum", "--out", str(tmp_path / "x.npz")])
    assert status == 130 and "cldyn record: interrupted" in err


def _pendulum_runs(runs: int, samples: int, dt: float) -> cldyn.Sequences:
    """Keypoint runs of a unit pendulum swinging about the origin (small-angle motion), one input."""
    t = dt * np.arange(samples)
    amplitude = np.linspace(0.2, 0.6, runs)[:, None]
    angle = amplitude * np.cos(np.sqrt(9.81) * t)[None, :]
    x = np.stack([np.sin(angle), -np.cos(angle)], axis=-1)
    return cldyn.Sequences(x, np.zeros((runs, samples, 1)), dt)


@pytest.fixture
def standard_promotion():
    # optax's cosine schedule (the command's learning-rate schedule) multiplies its int32 step count
    # by Python floats, which the suite's strict dtype promotion refuses.
    with jax.numpy_dtype_promotion("standard"):
        yield


class _InterruptAt(cldyn.AbstractProgressMeter):
    """A progress meter that presses Ctrl-C when the fit reports step `step`."""

    step: int

    def start(self, total, *, initial=0, desc="", unit="step"):
        return None

    def update(self, state, done, info=None):
        if done >= self.step:
            raise KeyboardInterrupt
        return state

    def close(self, state):
        pass


def test_fit_resume_overwrite_and_interrupt(tmp_path, capsys, monkeypatch, standard_promotion):
    data = _pendulum_runs(4, 10, 0.02).save(tmp_path / "runs.npz")
    out = tmp_path / "fit"
    common = ["fit", "--data", str(data), "--constraint", "pendulum", "--out", str(out), "--no-progress"]
    common += ["--validation-runs", "1", "--batch-size", "2", "--checkpoint-every", "2"]
    status, stdout, err = _run(capsys, common + ["--steps", "2", "--width", "8"])
    assert status == 0, err
    assert json.loads(stdout.splitlines()[-1])["steps"] == 2
    umask = os.umask(0)
    os.umask(umask)
    for file in out.iterdir():  # the files honour the umask, as open() would
        assert stat.S_IMODE(file.stat().st_mode) == 0o666 & ~umask, file
    fit_json = (out / "fit.json").read_text()
    # the fit is neither replaced nor resumed with other options unless asked to
    status, _, err = _run(capsys, common + ["--steps", "2", "--width", "8"])
    assert status == 2 and "fit.json" in err and "--resume" in err and "--overwrite" in err
    status, _, err = _run(capsys, common + ["--steps", "4", "--width", "8", "--resume"])
    assert status == 2 and "cldyn fit: error: --resume: the options differ" in err
    assert "steps 2 -> 4" in err and "--force" in err
    assert (out / "fit.json").read_text() == fit_json

    # --overwrite with another width, interrupted at step 4: the first model stays loadable
    monkeypatch.setattr(fit_command, "_meter", lambda args: _InterruptAt(4))
    replacing = common + ["--steps", "6", "--width", "16", "--validate-every", "2", "--overwrite"]
    status, _, err = _run(capsys, replacing)
    assert status == 130
    assert f"cldyn fit: interrupted; the last checkpoint is {out / 'checkpoint.eqx'} (step 4 of 6)" in err
    resume = shlex.split(err.strip().splitlines()[-1])
    assert resume[0] == "cldyn" and "--resume" in resume and "--force" in resume
    assert "--overwrite" not in resume
    model, spec = cldyn.load_fit(out)
    assert spec["model"]["width"] == 8 and isinstance(model, cldyn.ConstrainedLagrangian)

    # the printed command continues it; fit.json then describes it and keeps the earlier settings
    monkeypatch.setattr(fit_command, "_meter", lambda args: cldyn.NoProgressMeter())
    status, stdout, err = _run(capsys, resume[1:])
    assert status == 0, err
    summary = json.loads(stdout.splitlines()[-1])
    assert summary["steps"] == 6 and summary["validation"] is not None
    model, spec = cldyn.load_fit(out)
    assert spec["model"]["width"] == 16 and spec["previous"]["model"]["width"] == 8
    assert spec["model"]["constraint"] == "pendulum"

    # a replacing fit that diverges leaves that one loadable too
    diverging = common + ["--steps", "6", "--width", "8", "--lr", "1e30", "--overwrite"]
    status, _, err = _run(capsys, diverging)
    assert status == 2 and "cldyn fit: error: fit: non-finite loss or gradient at step" in err
    assert cldyn.load_fit(out)[1]["model"]["width"] == 16

    # a KeyCLD model without constraints, or with a scene's constraints that do not fit the data,
    # is an expected failure before any training, not a traceback
    for extra, message in (([], "needs a constraint"), (["--constraint", "acrobot"], "--constraint acrobot")):
        bad = ["fit", "--data", str(data), "--out", str(tmp_path / "bad"), "--validation-runs", "1"]
        status, _, err = _run(capsys, bad + ["--batch-size", "2"] + extra)
        assert status == 2 and "cldyn fit: error:" in err and message in err
    assert not (tmp_path / "bad").exists()


@pytest.mark.mujoco
def test_record_and_validate(tmp_path, capsys):
    pytest.importorskip("mujoco")
    from cldyn.mujoco import keycld_origin

    path = tmp_path / "pendulum.npz"
    argv = ["record", "--mjcf", "keycld/pendulum", "--out", str(path), "--runs", "2", "--duration", "0.2"]
    status, out, _ = _run(capsys, argv + ["--dt", "0.02", "--seed", "3"])
    assert status == 0 and out.startswith("recorded 2 runs x 11 samples (dt 0.02 s")
    status, _, err = _run(capsys, argv + ["--dt", "0.02", "--seed", "4"])
    assert status == 2 and "already exists" in err and cldyn.Sequences.load(path).info["seed"] == 3
    status, _, err = _run(capsys, argv + ["--dt", "0.02", "--seed", "3", "--overwrite"])
    assert status == 0, err
    data = cldyn.Sequences.load(path)
    assert data.x.shape == (2, 11, 2) and data.info["mjcf"] == "keycld/pendulum" and data.info["seed"] == 3
    # the single keypoint is the pole's tip: it stays on a circle about the pivot
    pivot = np.asarray(keycld_origin("pendulum"))
    radius = np.linalg.norm(np.asarray(data.x) - pivot, axis=-1)
    assert np.ptp(radius) < PENDULUM_TOL

    out_dir = tmp_path / "validation"
    argv = [
        "validate",
        "--mjcf",
        "keycld/pendulum",
        "--out",
        str(out_dir),
        "--runs",
        "1",
        "--duration",
        "0.1",
    ]
    status, out, err = _run(capsys, argv + ["--physics-dt", "0.001", "--tolerance", str(VALIDATE_TOL)])
    assert status == 0, err
    summary = json.loads(out.splitlines()[0])
    assert summary["runs"] == 1 and summary["max_position_error"] < VALIDATE_TOL
    assert (out_dir / "validation.json").is_file() and (out_dir / "keypoint_error.png").is_file()


@pytest.mark.mujoco
def test_control(tmp_path, capsys):
    pytest.importorskip("mujoco")
    argv = [
        "control",
        "--mjcf",
        "keycld/pendulum",
        "--out",
        str(tmp_path),
        "--runs",
        "2",
        "--duration",
        "0.6",
    ]
    status, out, _ = _run(capsys, argv)
    assert status == 0 and out.startswith("keycld/pendulum: ")
    report = json.loads((tmp_path / "control.json").read_text())
    assert report["runs"] == 2 and len(report["final_error"]) == 2
    assert (tmp_path / "control.png").is_file()
    # the controller needs every joint actuated: the stock acrobot is refused by name
    status, _, err = _run(capsys, ["control", "--mjcf", "acrobot", "--out", str(tmp_path / "a")])
    assert status == 2 and "cldyn control: error: swing_up needs a fully actuated scene" in err
    # and a model with an energy: a NODE2 fit (fit.json and model.eqx as cldyn fit writes them) is refused
    spec = {"kind": "node2", "size": 2, "num_inputs": 1, "constraint": None, "width": 4, "depth": 1}
    node2 = tmp_path / "node2"
    node2.mkdir()
    (node2 / "fit.json").write_text(json.dumps({"model": spec, "dtype": "float64"}))
    eqx.tree_serialise_leaves(node2 / "model.eqx", cldyn.model_from_spec(spec, key=jax.random.key(0)))
    argv = ["control", "--mjcf", "keycld/pendulum", "--out", str(tmp_path / "n"), "--model", str(node2)]
    status, _, err = _run(capsys, argv)
    assert status == 2 and "cldyn control: error: swing_up needs a ConstrainedLagrangian" in err
    assert not (tmp_path / "n").exists()


@pytest.mark.mujoco
@pytest.mark.slow
def test_identify(tmp_path, capsys):
    pytest.importorskip("mujoco")
    path = tmp_path / "pendulum.npz"
    argv = [
        "record",
        "--mjcf",
        "pendulum",
        "--out",
        str(path),
        "--runs",
        "6",
        "--duration",
        "2",
        "--dt",
        "0.01",
    ]
    assert _run(capsys, argv + ["--physics-dt", "0.002", "--integrator", "rk4", "--noise", "0.001"])[0] == 0
    argv = ["identify", "--data", str(path), "--model", "pendulum", "--out", str(tmp_path / "report")]
    argv += ["--effects", "joint_damping", "joint_spring", "--bootstrap", "10", "--max-rounds", "1"]
    status, out, _ = _run(capsys, argv)
    assert status == 0
    assert out.startswith("identify: 6 runs (4 fit, 2 held out) of 201 samples every 10 ms\n  noise ")
    assert "\n  before: accel_rmse " in out and "identify took" in out
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["settings"]["effects"] == ["joint_damping", "joint_spring"]
    assert (tmp_path / "report" / "report.md").is_file()
    # dm_control's pendulum damps its hinge (0.1 N m s), which the model from the same MJCF leaves out
    assert [(d["effect"], d["where"]) for d in report["detected"]] == [("joint_damping", "hinge")]
    assert "detected joint_damping at hinge" in out


@pytest.mark.mujoco
def test_fit_refuses_keypoints_off_the_model_constraints(tmp_path, capsys):
    # a pendulum pivoting 1.2 m above the origin: KeyCLD's pendulum constraint (the tip at a fixed
    # distance from the origin) does not hold unless --origin moves the pivot there
    pytest.importorskip("mujoco")
    xml = (
        '<mujoco><option timestep="0.005"/><worldbody><body name="arm" pos="0 0 1.2">'
        '<joint name="pivot" type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -0.75" '
        'size="0.02" mass="1"/></body></worldbody><actuator><motor joint="pivot" gear="2"/></actuator>'
        "</mujoco>"
    )
    (tmp_path / "pendulum.xml").write_text(xml)
    path = tmp_path / "runs.npz"
    argv = ["record", "--mjcf", str(tmp_path / "pendulum.xml"), "--out", str(path), "--runs", "6"]
    assert _run(capsys, argv + ["--duration", "0.5", "--dt", "0.02"])[0] == 0
    fit = ["fit", "--data", str(path), "--constraint", "pendulum", "--out", str(tmp_path / "f")]
    fit += ["--no-progress", "--validation-runs", "2", "--batch-size", "2", "--steps", "1"]
    status, _, err = _run(capsys, fit)
    assert status == 2 and "cldyn fit: error: the data do not fit --constraint pendulum" in err
    assert "Anchor(keypoint=0" in err and "pass --origin X Y" in err
    assert not (tmp_path / "f").exists()
    # about the pivot, the tip keeps its distance (to rounding: the data are noise-free)
    data = cldyn.Sequences.load(path)
    radius = np.linalg.norm(np.asarray(data.x) - np.array([0.0, 1.2]), axis=-1)
    assert np.ptp(radius) < PENDULUM_TOL
    assert cldyn.check_constraints(cldyn.Anchor(0), data.relative_to((0.0, 1.2)).x, noise=0.0).ok
