"""How exact a learnt estimator's keypoints are as geometry, and what that costs a physical model.

A diagnostic of the models learnt from images (issue 14: the acrobot's swing-up from frames), using
the ground truth stored beside the frames (never used for training). For one scene and model:

1. The estimator's keypoints on the training frames against MuJoCo's (through the camera into the
   image frame): the residual of the best affine map between them (pixels), how much the distances
   that the scene keeps constant vary along the data (relative standard deviation), and each joint
   coordinate of `cldyn.keycld_joints(scene)` read from the estimator's keypoints minus the same
   coordinate read from MuJoCo's, by the true coordinate's value (a warp: a systematic error that an
   affine map cannot remove); for each hinge, where the estimator puts its child segment's head in the
   true segment's frame (along and across it, in segment lengths, after the estimator's overall scale).
2. The structured dynamics (`cldyn.keycld_model(..., mass="coupled", potential="gravity",
   joints=keycld_joints(scene))`, exact for rigid bodies in uniform gravity) fitted with the recipe
   of `keyvision train`'s dynamics stages (collocation, then multiple shooting over half a run, peak
   learning rate 1e-2) to three sets of keypoints: MuJoCo's, MuJoCo's with white noise of the
   estimator's affine residual, and the estimator's. Each fit's gravity rates at the upright posture
   (the eigenvalues of d(acceleration)/dx on the constraints' tangent space, without control) beside
   MuJoCo's (`keyvision.target_linearisation`). Energy shaping with `kp = 5` holds the target only
   while the learnt rates are within `kp` of the truth.

Writes benchmarks/results/vision_geometry_<name>.json, .md and .png (each joint coordinate's error
against its true value; `--name`: the model directory's name by default); prints the JSON.

    python benchmarks/vision_geometry.py --scene acrobot \
        --model benchmarks/results/vision_models/acrobot-structured --data runs/acrobot-data
    # writes vision_geometry_acrobot-structured.{json,md,png}
"""

import argparse
import os
import pathlib
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, write  # noqa: E402

BINS = 12  # bins of a joint coordinate's value for its warp


def _joint_values(joints, x):
    import jax
    import jax.numpy as jnp

    values = jax.vmap(lambda z: jnp.stack([joint(z) for joint in joints]))(jnp.asarray(x))
    return np.asarray(values, np.float64)


def _rates(dynamics, at) -> list[float]:
    import jax
    import jax.numpy as jnp

    at = jnp.asarray(at)
    _, _, vh = np.linalg.svd(np.asarray(dynamics.constraint.jacobian(at), np.float64))
    tangent = vh[dynamics.num_constraints :].T
    controls = jnp.zeros(dynamics.num_inputs, at.dtype)
    stiffness = jax.jacfwd(lambda z: dynamics.acceleration(z, jnp.zeros_like(z), controls))(at)
    rates = np.linalg.eigvals(tangent.T @ np.asarray(stiffness, np.float64) @ tangent).real
    return np.sort(rates)[::-1].tolist()


def _plot(path, joints, q_true, q_est, warp) -> None:
    """Each joint coordinate's error (estimator minus MuJoCo) against its true value."""
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(joints), figsize=(4.5 * len(joints), 3.2), layout="constrained")
    pick = np.random.default_rng(0).choice(q_true.shape[0], min(4000, q_true.shape[0]), replace=False)
    for j, (axis, record) in enumerate(zip(np.atleast_1d(axes), warp)):
        error = q_est[:, j] - q_true[:, j]
        value = q_true[:, j]
        if record["unit"] == "deg":
            error = np.degrees((error + np.pi) % (2 * np.pi) - np.pi)
            value = np.degrees(value)
        edges = np.asarray(record["bin_edges"])
        centres = (edges[:-1] + edges[1:]) / 2
        if record["unit"] == "deg":
            centres = np.degrees(centres)
        means = [np.nan if m is None else m for m in record["mean_error_by_value"]]
        axis.scatter(value[pick], error[pick], s=2, alpha=0.3, color="0.5")
        axis.plot(centres, means, "o-", color="C3", label="mean in bin")
        axis.axhline(0.0, color="k", linewidth=0.8)
        unit = record["unit"]
        axis.set(xlabel=f"true joint {record['joint']} ({unit})", ylabel=f"estimator - true ({unit})")
        axis.legend(loc="upper right", fontsize=8)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def run(scene: str, model_dir: pathlib.Path, data: pathlib.Path, steps: int, seed: int, name: str) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import cldyn
    import keyvision
    from keyvision import _control, _train
    from keyvision._data import as_images
    from keyvision._files import trained_supersample

    model, spec = keyvision.load_model(model_dir)
    supersample = trained_supersample(spec)  # the camera the model was trained on
    frames = keyvision.Frames.load(data / "frames.npz" if data.is_dir() else data)
    train, _ = frames.split()
    started = time.perf_counter()
    sequences = keyvision.ImageSequences.from_frames(train)
    estimated = np.asarray(keyvision.encode_sequences(model, sequences).x, np.float64)
    points = train.extras["keypoints"]
    truth = train.camera.to_image(points.reshape(*points.shape[:2], -1, 2)).reshape(*points.shape[:2], -1)
    k = truth.shape[-1]
    size = frames.image_size[0]
    pixels = size / 2  # the image frame spans [-1, 1]

    # 1. geometry
    flat_true, flat_est = truth.reshape(-1, k), estimated.reshape(-1, k)
    design = np.concatenate([flat_true, np.ones((flat_true.shape[0], 1))], axis=1)
    affine, *_ = np.linalg.lstsq(design, flat_est, rcond=None)
    residual = (design @ affine - flat_est).reshape(flat_est.shape[0], -1, 2)
    residual_px = (np.linalg.norm(residual, axis=-1).mean(axis=0) * pixels).tolist()
    scale = float((flat_est * flat_true).sum() / (flat_true * flat_true).sum())  # the estimator's size
    constraint = cldyn.keycld_constraint(scene)
    drift = {}
    for source, x in (("mujoco", flat_true), ("estimator", flat_est)):
        values = np.asarray(jax.vmap(constraint)(jnp.asarray(x)), np.float64)
        drift[source] = (values.std(axis=0) / np.maximum(np.abs(values.mean(axis=0)), 1e-12)).tolist()
    joints = cldyn.keycld_joints(scene)
    q_true, q_est = _joint_values(joints, flat_true), _joint_values(joints, flat_est)
    warp = []
    for j, joint in enumerate(joints):
        error = q_est[:, j] - q_true[:, j]
        if isinstance(joint, cldyn.HingeAngle):
            error = (error + np.pi) % (2 * np.pi) - np.pi
            edges = np.linspace(-np.pi, np.pi, BINS + 1)
            unit = "deg"
            error = np.degrees(error)
        else:
            edges = np.quantile(q_true[:, j], np.linspace(0, 1, BINS + 1))
            unit = "image units"
        index = np.clip(np.digitize(q_true[:, j], edges) - 1, 0, BINS - 1)
        means = [float(error[index == b].mean()) if (index == b).any() else None for b in range(BINS)]
        record = {
            "joint": f"{j}: {type(joint).__name__}",
            "unit": unit,
            "rms": float(np.sqrt(np.mean(error**2))),
            "bin_edges": edges.tolist(),
            "mean_error_by_value": means,
            "largest_bin_mean": float(max(abs(m) for m in means if m is not None)),
        }
        if isinstance(joint, cldyn.HingeAngle) and joint.child[1] is not None:
            # where the estimator puts the child segment's head, in the true segment's frame (from
            # its true tail, along it and across it, in segment lengths), after the similarity scale
            tail, head = (
                np.broadcast_to(np.asarray(joint.pivot), (flat_true.shape[0], 2)) if i is None
                else flat_true[:, 2 * i : 2 * i + 2]
                for i in joint.child
            )
            estimated_head = flat_est[:, 2 * joint.child[1] : 2 * joint.child[1] + 2] / scale
            length = np.linalg.norm(head - tail, axis=1, keepdims=True)
            along = (head - tail) / length
            across = np.stack([-along[:, 1], along[:, 0]], axis=1)
            offset = estimated_head - tail
            for key, axis in (("head_along_by_value", along), ("head_across_by_value", across)):
                share = (offset * axis).sum(axis=1) / length[:, 0]
                record[key] = [
                    float(share[index == b].mean()) if (index == b).any() else None for b in range(BINS)
                ]
        warp.append(record)

    _plot(RESULTS / f"vision_geometry_{name}.png", joints, q_true, q_est, warp)

    # 2. the structured dynamics fitted to each set of keypoints
    mujoco = _control._mujoco()
    _, setup = _control._model_scene(model, f"keycld/{scene}", "fixed", "vision_geometry", supersample)
    view = _control.PlanarCamera(setup.homography, setup.basis)
    state = mujoco.MjData(setup.model)
    _, upright = _control._postures(mujoco, setup, state, view)
    pose = keyvision.render_poses(f"keycld/{scene}", upright[None], supersample=supersample)
    upright_true = view.to_image(np.asarray(pose["keypoints"][0]).reshape(-1, 2)).reshape(-1)
    upright_est = np.asarray(model.encode(as_images(pose["frames"][0])), np.float64)
    true_rates = keyvision.target_linearisation(model, f"keycld/{scene}", supersample=supersample)[
        "gravity_rates"
    ]
    sigma = float(np.sqrt(np.mean(residual**2)))
    noisy = truth + np.random.default_rng(seed).normal(0.0, sigma, truth.shape)
    u = train.u.astype(np.float64)
    fits = []
    for source, x, at in (
        ("mujoco", truth, upright_true),
        ("mujoco + white noise", noisy, upright_true),
        ("estimator", estimated, upright_est),
    ):
        dynamics = cldyn.keycld_model(
            k, u.shape[-1], constraint, key=jax.random.key(seed), mass="coupled", potential="gravity",
            joints=joints,
        )
        dynamics = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, dynamics)
        sequences = cldyn.Sequences(jnp.asarray(x), jnp.asarray(u), frames.dt)
        for number, loss in enumerate(
            (cldyn.Collocation(), cldyn.MultipleShooting(segment=max(1, (x.shape[1] - 3) // 2)))
        ):
            dynamics = cldyn.fit(
                dynamics, sequences, loss=loss, steps=steps, key=jax.random.key(seed + 1 + number),
                optimizer=_train._adam(keyvision.Schedule(), 1e-2, steps),
                batching=cldyn.Runs(min(32, sequences.num_runs)),
            ).model
        rates = _rates(dynamics, at)
        fits.append(
            {
                "keypoints": source,
                "gravity_rates_at_upright": rates,
                "relative_error_of_fastest": float(rates[0] / true_rates[0] - 1),
            }
        )
        print(scene, source, rates, flush=True)
    return {
        "scene": scene,
        "model": str(model_dir),
        "data": str(data),
        "training_runs": int(truth.shape[0]),
        "affine_residual_px": residual_px,
        "noise_sigma_px": sigma * pixels,
        "constraint_relative_std": drift,
        "similarity_scale": scale,
        "joint_warp": warp,
        "mujoco_gravity_rates": true_rates,
        "curvature_tolerance": float(5.0 / true_rates[0]),
        "fits": fits,
        "steps_per_fit": steps,
        "seconds": round(time.perf_counter() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", required=True, choices=("pendulum", "cartpole", "acrobot"))
    parser.add_argument("--model", required=True, help="a keyvision train output directory")
    parser.add_argument("--data", required=True, help="its training frames (frames.npz or its folder)")
    parser.add_argument("--steps", type=int, default=2000, help="steps of each of the two fits")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", help="the results' name (default: the model directory's)")
    args = parser.parse_args()
    name = args.name or pathlib.Path(args.model).resolve().name
    row = run(args.scene, pathlib.Path(args.model), pathlib.Path(args.data), args.steps, args.seed, name)
    result = {"machine": machine(), **row}
    lines = [
        f"# Keypoint geometry of a model learnt from images: {args.scene}",
        "",
        f"Model `{row['model']}`, its {row['training_runs']} training runs "
        f"(`benchmarks/vision_geometry.py`). Estimator against MuJoCo's keypoints: affine residual "
        + ", ".join(f"{v:.2f}" for v in row["affine_residual_px"])
        + " px per keypoint; the scene's constant distances vary by "
        + ", ".join(f"{100 * v:.1f}%" for v in row["constraint_relative_std"]["estimator"])
        + " (relative std along the data; MuJoCo's "
        + ", ".join(f"{100 * v:.1f}%" for v in row["constraint_relative_std"]["mujoco"])
        + ").",
        "",
        "| joint | error rms | largest mean error in a bin of the true value | unit | child's head across "
        "its true segment, by bin (segment lengths) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for warp in row["joint_warp"]:
        across = warp.get("head_across_by_value")
        across = "-" if across is None else " ".join("-" if a is None else f"{a:+.3f}" for a in across)
        cells = (warp["joint"], f"{warp['rms']:.3g}", f"{warp['largest_bin_mean']:.3g}", warp["unit"], across)
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "Structured dynamics fitted to each set of keypoints: gravity's rates at upright (1/s²) against "
        "MuJoCo's " + ", ".join(f"{r:.2f}" for r in row["mujoco_gravity_rates"])
        + f" (kp = 5 tolerates {100 * row['curvature_tolerance']:.0f}% on the fastest). White noise: "
        f"{row['noise_sigma_px']:.2f} px per coordinate.",
        "",
        "| keypoints | rates at upright | fastest vs MuJoCo |",
        "| --- | --- | --- |",
    ]
    for fit in row["fits"]:
        rates = ", ".join(f"{r:.2f}" for r in fit["gravity_rates_at_upright"])
        lines.append(f"| {fit['keypoints']} | {rates} | {100 * fit['relative_error_of_fastest']:+.1f}% |")
    write(f"vision_geometry_{name}", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
