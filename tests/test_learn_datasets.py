"""KeyCLD datasets recorded with MuJoCo (appendix A.6), and the `cldyn fit` command line."""

import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
from cldyn._cli import main

mujoco = pytest.importorskip("mujoco")
import cldyn.mujoco as cm  # noqa: E402

pytestmark = pytest.mark.mujoco

CONSTRAINT_TOL = 1e-6


@pytest.mark.parametrize(
    "scene, dt, k, inputs", [("pendulum", 0.02, 2, 1), ("cartpole", 0.01, 4, 2), ("acrobot", 0.01, 4, 2)]
)
def test_keycld_datasets_follow_the_protocol(tmp_path, scene, dt, k, inputs):
    data = cm.keycld_dataset(scene, runs=10, frames=8, seed=3, cache=tmp_path)
    assert (data.num_runs, data.num_samples, data.size, data.num_inputs) == (10, 8, k, inputs)
    assert data.dt == pytest.approx(dt)
    # one constant control per run, zero in 20% of the runs
    np.testing.assert_array_equal(data.u, np.broadcast_to(data.u[:, :1], data.u.shape))
    assert int(np.sum(np.all(data.u[:, 0] == 0, axis=1))) == 2
    assert np.all(np.abs(data.u) <= 2.0)
    # keypoints about the first joint: the paper's constraints hold with constant values
    constraint = cldyn.keycld_constraint(scene)
    values = jax.jit(jax.vmap(jax.vmap(constraint)))(jnp.asarray(data.x))
    np.testing.assert_allclose(values, np.broadcast_to(values[:, :1], values.shape), atol=CONSTRAINT_TOL)
    if scene == "cartpole":
        np.testing.assert_allclose(data.x[..., 1], 0.0, atol=CONSTRAINT_TOL)
    else:
        np.testing.assert_allclose(values[..., 0], 0.5 if scene == "pendulum" else 1.0, atol=CONSTRAINT_TOL)


def test_dataset_seed_noise_and_cache(tmp_path):
    first = cm.keycld_recording("pendulum", runs=6, frames=5, noise=0.01, seed=1, cache=tmp_path)
    again = cm.keycld_recording("pendulum", runs=6, frames=5, noise=0.01, seed=1, cache=tmp_path)
    np.testing.assert_array_equal(first.x, again.x)
    for name, value in first.extras.items():
        np.testing.assert_array_equal(again.extras[name], value)
    assert first.info == again.info
    assert first.info["seed"] == 1 and first.info["noise"] == 0.01 and first.info["mjcf"] == "keycld/pendulum"
    noise = first.x - first.extras["x_clean"]
    assert 0.003 < float(np.std(noise)) < 0.03
    other = cm.keycld_recording("pendulum", runs=6, frames=5, noise=0.01, seed=2, cache=False)
    assert not np.array_equal(first.extras["x_clean"], other.extras["x_clean"])
    # the dataset for learning: the same runs about the pivot, without MuJoCo's joint-space arrays
    data = cm.keycld_dataset("pendulum", runs=6, frames=5, noise=0.01, seed=1, cache=tmp_path)
    origin = cm.keycld_origin("pendulum")
    np.testing.assert_array_equal(data.x, first.x - origin)
    np.testing.assert_array_equal(data.xdd, first.xdd)
    assert data.extras == {} and data.info["origin"] == tuple(origin) and data.info["seed"] == 1
    (cached,) = tmp_path.glob("keycld-pendulum-*.npz")
    cached.write_bytes(b"corrupt")
    with pytest.warns(UserWarning, match="unreadable cached dataset"):
        regenerated = cm.keycld_recording("pendulum", runs=6, frames=5, noise=0.01, seed=1, cache=tmp_path)
    np.testing.assert_array_equal(regenerated.x, first.x)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cm.keycld_recording("pendulum", runs=6, frames=5, noise=0.01, seed=1, cache=tmp_path)


def test_cli_fit_resume_and_load(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CLDYN_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "fit"
    common = ["fit", "--scene", "pendulum", "--runs", "12", "--frames", "12", "--validation-runs", "2",
              "--out", str(out), "--no-progress", "--checkpoint-every", "5", "--validate-every", "5",
              "--batch-size", "8"]
    assert main(common + ["--steps", "5"]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert first["steps"] == 5
    # more steps is a changed setting: refused on resume unless forced
    assert main(common + ["--steps", "10", "--resume"]) == 2
    assert "steps 5 -> 10" in capsys.readouterr().err
    assert main(common + ["--steps", "10", "--resume", "--force"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["steps"] == 10 and summary["validation"] is not None
    model, spec = cldyn.load_fit(out)
    assert isinstance(model, cldyn.ConstrainedLagrangian) and spec["model"]["constraint"] == "pendulum"
    assert json.loads((out / "history.json").read_text())["records"][-1]["step"] == 10
    x = np.zeros((3, 8, 2)) + np.linspace(0, 0.1, 8)[None, :, None]
    data = cldyn.Sequences(x, np.zeros((3, 1)), 0.02)
    path = data.save(tmp_path / "runs.npz")
    assert main(["fit", "--data", str(path), "--model", "node2", "--validation-runs", "1", "--steps", "2",
                 "--out", str(tmp_path / "node2"), "--no-progress", "--batch-size", "2"]) == 0
    assert main(["fit", "--data", str(path), "--model", "keycld", "--steps", "2", "--validation-runs", "1",
                 "--out", str(tmp_path / "bad"), "--no-progress", "--batch-size", "2"]) == 2
    assert "needs a constraint" in capsys.readouterr().err
