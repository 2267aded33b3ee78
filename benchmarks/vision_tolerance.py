"""What the valid prediction time asks of a model's keypoints, in pixels, scene by scene.

The VPT (eq. 16) ends at the first predicted frame whose mean squared error exceeds a threshold,
the error of the static mean image (`keyvision.prediction_threshold`). How far a predicted keypoint
may stray before that happens depends on the scene: on how much of the image its bodies cover
against how much their motion blurs the mean image. For each scene and model this measures, on the
50 validation runs of the paper's protocol (issue 13: why the rows differ):

1. The scene's own tolerance, no model: pairs of true frames of one run up to ten frames apart,
   the distance their true keypoints (MuJoCo's, through the camera) moved against the error between
   the two frames; the share of pairs over the threshold by distance, and the distance at which half
   of them cross it.
2. The model's tolerance. The model's renderer draws each validation frame from the estimator's
   keypoints moved by a fixed offset: every keypoint by the same length, along its own motion or in a
   random direction (a keypoint that does not move between the neighbouring frames stays). Reported:
   the share of frames whose error against the true frame exceeds the threshold, and the median
   error over the threshold. The tolerance is the offset at which half of the frames cross it (along
   the motion, interpolated): the keypoint error that ends a VPT, in the estimator's pixels (its
   keypoints need not sit on the bodies' points, so this differs from the scene's tolerance by the
   estimator's scale).
3. The model's own predictions (`keyvision.predict`, the first three frames encoded): the VPT, and
   the distance in pixels between the predicted keypoints and the estimator's keypoints of the true
   frames a quarter of the way into the prediction, half way and at its end (median over runs; the
   runs last 1 s on the pendulum, 0.5 s on the others), and at the frame where each run's VPT ends.

Writes benchmarks/results/vision_tolerance.json, .md and .png (error over the threshold against the
offset, one line per scene); prints the JSON.

    python benchmarks/vision_tolerance.py        # the three scenes, their committed models
    python benchmarks/vision_tolerance.py --scenes pendulum --models runs/pendulum \\
        --data runs/pendulum-data/frames.npz
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
from _common import RESULTS, VISION_MODELS, machine, write  # noqa: E402

OFFSETS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)  # pixels
SAMPLE_FRAMES = 400  # validation frames drawn for the offsets
PARTS = (0.25, 0.5, 1.0)  # how far into the prediction the error is read: a quarter, half, the end


def _crossing(offsets, shares) -> float | None:
    """The offset at which the share over the threshold reaches one half (linear between samples)."""
    for (a, sa), (b, sb) in zip(zip(offsets, shares), zip(offsets[1:], shares[1:])):
        if sa < 0.5 <= sb:
            return float(a + (b - a) * (0.5 - sa) / (sb - sa))
    return None


def scene_tolerance(images, truth, threshold: float, offsets, lags: int = 10) -> dict:
    """Step 1: pairs of true frames against the distance their true keypoints moved."""
    pixels = images.shape[-2] / 2
    count = truth.shape[-1] // 2
    moved, ratio = [], []
    for lag in range(1, lags + 1):
        step = np.linalg.norm((truth[:, lag:] - truth[:, :-lag]).reshape(-1, count, 2), axis=-1).max(axis=-1)
        error = np.mean((images[:, lag:] - images[:, :-lag]) ** 2, axis=(-3, -2, -1)).reshape(-1)
        moved.append(step * pixels)
        ratio.append(error / threshold)
    moved, ratio = np.concatenate(moved), np.concatenate(ratio)
    shares, medians, pairs = [], [], []
    for centre in offsets:  # pairs within a quarter pixel of each offset
        near = np.abs(moved - centre) <= 0.125 if centre > 0 else moved <= 0.125
        pairs.append(int(near.sum()))
        shares.append(float(np.mean(ratio[near] > 1)) if near.any() else None)
        medians.append(float(np.median(ratio[near])) if near.any() else None)
    known = [(o, s) for o, s in zip(offsets, shares) if s is not None]
    return {
        "offsets_px": list(offsets),
        "pairs": pairs,
        "share_over_threshold": shares,
        "median_over_threshold": medians,
        "tolerance_px": _crossing([o for o, _ in known], [s for _, s in known]),
    }


def tolerance(model, images, keypoints, threshold: float, offsets, seed: int) -> dict:
    """Step 2: frames drawn from offset keypoints against the true frames."""
    import jax.numpy as jnp

    from keyvision._evaluate import decode_batch

    pixels = images.shape[-2] / 2  # the image frame spans [-1, 1]
    count = keypoints.shape[-1] // 2
    x = keypoints[:, 1:-1].reshape(-1, keypoints.shape[-1])
    motion = (keypoints[:, 2:] - keypoints[:, :-2]).reshape(-1, keypoints.shape[-1])
    truth = images[:, 1:-1].reshape(-1, *images.shape[2:])
    rng = np.random.default_rng(seed)
    pick = rng.choice(x.shape[0], min(SAMPLE_FRAMES, x.shape[0]), replace=False)
    x, motion, truth = x[pick], motion[pick], truth[pick]
    directions = {"motion": motion.reshape(-1, count, 2), "random": rng.normal(size=(x.shape[0], count, 2))}
    record = {}
    for name, direction in directions.items():
        unit = direction / np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)
        medians, shares = [], []
        for offset in offsets:
            moved = x + (offset / pixels) * unit.reshape(x.shape)
            drawn = np.asarray(decode_batch(model, jnp.asarray(moved, jnp.float32)))
            ratio = np.mean((drawn - truth) ** 2, axis=(1, 2, 3)) / threshold
            medians.append(float(np.median(ratio)))
            shares.append(float(np.mean(ratio > 1)))
        record[name] = {"median_over_threshold": medians, "share_over_threshold": shares}
    record["offsets_px"] = list(offsets)
    record["frames"] = int(x.shape[0])
    record["tolerance_px"] = _crossing(offsets, record["motion"]["share_over_threshold"])
    record["tolerance_random_px"] = _crossing(offsets, record["random"]["share_over_threshold"])
    return record


def predictions(model, images, controls, keypoints, dt: float, threshold: float) -> dict:
    """Step 3: the model's predictions against the estimator's keypoints of the true frames."""
    import keyvision
    from keyvision._evaluate import predict_runs

    pixels = images.shape[-2] / 2
    count = keypoints.shape[-1] // 2
    predicted, frames = predict_runs(model, images, controls, dt)
    vpt = np.asarray(keyvision.valid_prediction_time(frames, images, threshold=threshold))
    distance = np.linalg.norm((predicted - keypoints).reshape(*predicted.shape[:2], count, 2), axis=-1)
    distance = distance.max(axis=-1) * pixels  # (runs, frames): the keypoint furthest off
    samples = images.shape[1]
    at_end = [distance[r, int(round(v * samples))] for r, v in enumerate(vpt) if v < 1]
    return {
        "vpt_mean": float(vpt.mean()),
        "vpt_median": float(np.median(vpt)),
        "error_px_at_frames": {
            str(frame): float(np.median(distance[:, frame]))
            for frame in (min(samples - 1, int(part * samples)) for part in PARTS)
        },
        "dt": dt,
        "error_px_where_vpt_ends": {
            "runs": len(at_end),
            "median": float(np.median(at_end)) if at_end else None,
        },
    }


def run(scene: str, model_dir: pathlib.Path, data: pathlib.Path | None, seed: int) -> dict:
    import jax.numpy as jnp

    import keyvision
    from keyvision._evaluate import encode_batch

    model, _ = keyvision.load_model(model_dir)
    if data is None:
        protocol = keyvision.RenderProtocol(image_size=model.image_size)
        frames = keyvision.render(f"keycld/{scene}", protocol=protocol, seed=0)
    else:
        frames = keyvision.Frames.load(data / "frames.npz" if data.is_dir() else data)
    _, validation = frames.split()
    started = time.perf_counter()
    images = validation.images(np.float32)
    controls = validation.u.astype(np.float32)
    threshold = keyvision.prediction_threshold(images)
    keypoints = np.stack([np.asarray(encode_batch(model, jnp.asarray(each))) for each in images])
    points = validation.extras["keypoints"]
    truth = validation.camera.to_image(points.reshape(*points.shape[:2], -1, 2)).reshape(
        *points.shape[:2], -1
    )
    record = {
        "scene": scene,
        "model": os.path.relpath(model_dir, ROOT),
        "runs": int(images.shape[0]),
        "frames": int(images.shape[1]),
        "threshold": threshold,
        "scene_tolerance": scene_tolerance(images, truth, threshold, OFFSETS),
        "tolerance": tolerance(model, images, keypoints, threshold, OFFSETS, seed),
        "predictions": predictions(model, images, controls, keypoints, validation.dt, threshold),
    }
    record["seconds"] = time.perf_counter() - started
    return record


def _plot(path: pathlib.Path, records: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True, layout="constrained")
    for i, record in enumerate(records):
        own = record["scene_tolerance"]
        known = [(o, m) for o, m in zip(own["offsets_px"], own["median_over_threshold"]) if m is not None]
        left.plot(*zip(*known), "-", color=f"C{i}", marker="o", markersize=3, label=record["scene"])
        tol = record["tolerance"]
        for name, style in (("motion", "-"), ("random", ":")):
            label = f"{record['scene']}, {'along the motion' if name == 'motion' else 'random direction'}"
            right.plot(
                tol["offsets_px"],
                tol[name]["median_over_threshold"],
                style,
                color=f"C{i}",
                marker="o",
                markersize=3,
                label=label,
            )
    for axis in (left, right):
        axis.axhline(1.0, color="k", linestyle="--", linewidth=1, label="VPT threshold")
        axis.legend(fontsize=7)
    left.set(
        xlabel="true keypoints moved (pixels)",
        ylabel="frame MSE / threshold (median)",
        title="true frames of one run, up to 10 apart",
    )
    right.set(xlabel="estimator's keypoints moved (pixels)", title="the model's renderer")
    figure.savefig(path, dpi=120)
    plt.close(figure)


def _markdown(result: dict) -> str:
    lines = [
        "# What the VPT asks of the keypoints (benchmarks/vision_tolerance.py)",
        "",
        "Scene's tolerance: over pairs of true frames of one validation run up to ten frames apart, the "
        "distance the true keypoints moved (MuJoCo's, through the camera; the one that moved most) at "
        "which half of the pairs differ by more than the VPT threshold: the pose error that ends a VPT, "
        "whatever the model. "
        f"Then {SAMPLE_FRAMES} validation frames per scene drawn by the model's renderer from the "
        "estimator's keypoints moved by a fixed offset (every keypoint, along its motion or in a random "
        "direction), against the true frames; then the model's own predictions of the 50 validation runs "
        "(`keyvision.predict`). Tolerance: the offset at which half of the frames exceed the VPT threshold. "
        "Error: the distance between the predicted keypoints and the estimator's keypoints of the true "
        "frames (the keypoint furthest off), median over runs.",
        "",
        "| scene | model | scene's tolerance (px) | share of frames over the threshold at 0.5 / 1 / 2 px "
        "(along the motion) | tolerance along the motion, random (px) | VPT mean, median | prediction "
        "error a quarter, half way and at the end (px; frames, s) | error where a VPT ends (px, runs) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in result["scenes"]:
        tol, pred = r["tolerance"], r["predictions"]
        share = dict(zip(tol["offsets_px"], tol["motion"]["share_over_threshold"]))
        fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        at = pred["error_px_at_frames"]
        frames = ", ".join(f"{int(f)} ({int(f) * pred['dt']:.2f} s)" for f in at)
        errors = " / ".join(f"{v:.2f}" for v in at.values())
        end = pred["error_px_where_vpt_ends"]
        scene_tol = fmt(r["scene_tolerance"]["tolerance_px"])
        lines.append(
            f"| {r['scene']} | `{r['model']}` | {scene_tol} | "
            f"{share[0.5]:.0%} / {share[1.0]:.0%} / {share[2.0]:.0%} | "
            f"{fmt(tol['tolerance_px'])}, {fmt(tol['tolerance_random_px'])} | "
            f"{pred['vpt_mean']:.3f}, {pred['vpt_median']:.3f} | "
            f"{errors} (frames {frames}) | {fmt(end['median'])} ({end['runs']}) |"
        )
    lines += [
        "",
        f"Machine: {result['machine']['platform']}, {result['machine']['cpus']} CPUs, "
        f"jax {result['machine']['jax']} {result['machine']['backend']}.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=["pendulum", "cartpole", "acrobot"],
        choices=("pendulum", "cartpole", "acrobot"),
    )
    parser.add_argument(
        "--models", nargs="+", help="a model directory per scene (default: the committed ones)"
    )
    parser.add_argument(
        "--data",
        nargs="+",
        help="frames.npz (or its folder) per scene, the paper's protocol "
        "(default: keyvision.render's, seed 0, from its cache when it is there)",
    )
    parser.add_argument("--seed", type=int, default=0, help="draws the frames and the random directions")
    parser.add_argument("--name", default="vision_tolerance", help="the results' file name")
    args = parser.parse_args()
    for option in ("models", "data"):
        given = getattr(args, option)
        if given is not None and len(given) != len(args.scenes):
            parser.error(f"--{option}: one per scene ({len(args.scenes)}), got {len(given)}")
    models = (
        [pathlib.Path(m) for m in args.models] if args.models else [VISION_MODELS[s] for s in args.scenes]
    )
    data = [pathlib.Path(d) for d in args.data] if args.data else [None] * len(args.scenes)
    records = []
    for scene, model_dir, frames in zip(args.scenes, models, data):
        records.append(run(scene, model_dir, frames, args.seed))
        print(
            f"{scene}: tolerance {records[-1]['tolerance']['tolerance_px']} px, "
            f"{records[-1]['seconds']:.0f} s",
            file=sys.stderr,
            flush=True,
        )
    result = {"benchmark": "vision_tolerance", "machine": machine(), "scenes": records}
    _plot(RESULTS / f"{args.name}.png", records)
    write(args.name, result, _markdown(result))


if __name__ == "__main__":
    main()
