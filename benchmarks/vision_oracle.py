"""Where KeyCLD's VPT is lost: the learnt dynamics against dynamics fitted to MuJoCo's own keypoints.

A diagnostic of `benchmarks/vision.py`'s models that uses the ground truth stored beside the frames
(never used for training). For each scene, fresh KeyCLD dynamics (`cldyn.keycld_model`, point
masses, the scene's constraints) are fitted with the recipe of `keyvision.train`'s stages (b) and (d)
(collocation, then multiple shooting over half a run) to the training runs' keypoints, taken either
from MuJoCo (its keypoints through the camera into the image frame: exact, rigid) or from the
model's estimator. The validation runs are then predicted from their first three frames'
keypoints and drawn by the model's renderer (MuJoCo's keypoints reach it through the affine map
that best fits the estimator's keypoints to them), and scored by the VPT, next to the trained model's
own. The keypoint columns give the rollout error in pixels: a dynamics model class that reaches VPT
1 from MuJoCo's keypoints puts the gap on the estimator, not on the dynamics.

Writes benchmarks/results/vision_oracle.json and .md, keeping the rows of the scenes not given; prints
the JSON.

    python benchmarks/vision_oracle.py --model cartpole=benchmarks/results/vision_models/cartpole
"""

import argparse
import json
import os
import pathlib
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, write  # noqa: E402

SCENES = ("pendulum", "cartpole", "acrobot")

FRAMES_AT = (10, 25, 49)  # frames at which the keypoint rollout error is reported


def scene(name: str, model_dir: pathlib.Path, data: pathlib.Path, steps: int) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax

    import cldyn
    import keyvision

    model, _ = keyvision.load_model(model_dir)
    frames = keyvision.Frames.load(data / "frames.npz" if data.is_dir() else data)
    train, validation = frames.split()
    encode = eqx.filter_jit(lambda m, z: jax.vmap(m.encode)(z))
    decode = eqx.filter_jit(lambda m, x: jax.vmap(m.decode)(x))

    def encoded(part):
        images = part.images(np.float32)
        return np.stack([np.asarray(encode(model, run)) for run in images]).astype(np.float64)

    def mujoco_keypoints(part):
        points = part.extras["keypoints"]
        image = part.camera.to_image(points.reshape(*points.shape[:2], -1, 2))
        return image.reshape(*points.shape[:2], -1)

    estimated = {"train": encoded(train), "validation": encoded(validation)}
    truth = {"train": mujoco_keypoints(train), "validation": mujoco_keypoints(validation)}
    k = truth["train"].shape[-1]
    flat = truth["train"].reshape(-1, k)
    design = np.concatenate([flat, np.ones((flat.shape[0], 1))], axis=1)
    affine, *_ = np.linalg.lstsq(design, estimated["train"].reshape(-1, k), rcond=None)
    images = validation.images(np.float32)
    threshold = keyvision.prediction_threshold(images)
    dt, u_train, u_val = frames.dt, train.u.astype(np.float32), validation.u.astype(np.float32)

    @eqx.filter_jit
    def rollout(dynamics, x, u):
        run = cldyn.rollout(
            dynamics, x[1], (x[2] - x[0]) / (2 * dt), u[1:], dt,
            solver=cldyn.RK4(), stabilisation=cldyn.Projection(), project=True,
        )
        return jnp.concatenate([x[:1], run.x], axis=0)

    def score(dynamics, source: str) -> dict:
        x = truth["validation"] if source == "mujoco" else estimated["validation"]
        predicted = np.stack(
            [np.asarray(rollout(dynamics, jnp.asarray(run, jnp.float32), u)) for run, u in zip(x, u_val)]
        ).astype(np.float64)
        error = np.linalg.norm((predicted - x).reshape(*x.shape[:2], -1, 2), axis=-1).mean(axis=(0, 2))
        if source == "mujoco":  # into the renderer's frame
            predicted = np.concatenate([predicted, np.ones((*predicted.shape[:2], 1))], axis=-1) @ affine
        drawn = np.stack([np.asarray(decode(model, jnp.asarray(run, jnp.float32))) for run in predicted])
        vpt = np.asarray(keyvision.valid_prediction_time(drawn, images, threshold=threshold))
        size = frames.image_size[0]
        return {
            "vpt": {"mean": float(vpt.mean()), "median": float(np.median(vpt))},
            "keypoint_error_px": {str(i): float(error[i] * size / 2) for i in FRAMES_AT},
        }

    def fitted(source: str):
        x = truth["train"] if source == "mujoco" else estimated["train"]
        data = cldyn.Sequences(jnp.asarray(x, jnp.float32), jnp.asarray(u_train), dt)
        dynamics = cldyn.keycld_model(
            k, u_train.shape[-1], cldyn.keycld_constraint(name), key=jax.random.key(0)
        )
        dynamics = jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, dynamics)
        batching = cldyn.Runs(min(32, data.num_runs))
        for loss, rate, seed in (
            (cldyn.Collocation(), 1e-3, 1),
            (cldyn.MultipleShooting(segment=max(1, (data.num_samples - 3) // 2)), 3e-4, 2),
        ):
            dynamics = cldyn.fit(
                dynamics, data, loss=loss, steps=steps, key=jax.random.key(seed),
                optimizer=optax.adam(rate), batching=batching,
            ).model
        return dynamics

    started = time.perf_counter()
    row = {"scene": name, "model": str(model_dir), "steps_per_fit": steps}
    row["learnt"] = score(model.dynamics, "estimator")
    for source in ("mujoco", "estimator"):
        row[f"fitted_to_{source}"] = score(fitted(source), source)
    row["seconds"] = round(time.perf_counter() - started, 1)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--model", action="append", required=True, metavar="SCENE=DIR", help="a model of SCENE (repeat)"
    )
    parser.add_argument("--data", default=str(ROOT / "runs" / "bench-vision"), help="holds <scene>/data")
    parser.add_argument("--steps", type=int, default=2000, help="steps of each of the two fits")
    args = parser.parse_args()
    import jax

    rows = []
    for given in args.model:
        name, _, directory = given.partition("=")
        rows.append(scene(name, pathlib.Path(directory), pathlib.Path(args.data) / name / "data", args.steps))
    # the rows of scenes not run this time are kept from the previous results (one scene per call fits)
    previous = RESULTS / "vision_oracle.json"
    if previous.is_file():
        run = {row["scene"] for row in rows}
        rows += [row for row in json.loads(previous.read_text())["scenes"] if row["scene"] not in run]
    rows.sort(key=lambda row: SCENES.index(row["scene"]) if row["scene"] in SCENES else len(SCENES))
    _write({"machine": machine(), "device": str(jax.devices()[0]), "scenes": rows})


def _write(result: dict) -> None:
    rows = result["scenes"]
    lines = [
        "# Where the VPT is lost: learnt dynamics against dynamics fitted to MuJoCo's keypoints",
        "",
        "VPT over the 50 validation runs, all drawn by the model's renderer; keypoint error: mean pixels "
        f"between the predicted and the given keypoints at frames {', '.join(map(str, FRAMES_AT))}. Fresh "
        "KeyCLD dynamics fitted (collocation, then multiple shooting) to the training runs' keypoints from "
        "MuJoCo or from the model's estimator.",
        "",
        "| scene | learnt model | fitted to MuJoCo's keypoints | fitted to the estimator's "
        "| error (px), MuJoCo's | error (px), estimator's |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        def errors(part):
            return " / ".join(f"{v:.2f}" for v in part["keypoint_error_px"].values())

        vpts = [row[part]["vpt"]["mean"] for part in ("learnt", "fitted_to_mujoco", "fitted_to_estimator")]
        cells = [row["scene"], *(f"{v:.3f}" for v in vpts)]
        cells += [errors(row["fitted_to_mujoco"]), errors(row["fitted_to_estimator"])]
        lines.append("| " + " | ".join(cells) + " |")
    write("vision_oracle", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
