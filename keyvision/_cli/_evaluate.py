"""`keyvision evaluate`: the valid prediction time of a trained model on the validation runs, the
error over time, a strip and a GIF of true and predicted frames with their keypoints, and how well the
keypoints track the true pose."""

import argparse
import json
import warnings

import numpy as np

from cldyn._cli._common import CommandError, add_command, add_overwrite, output_directory, positive

from ._common import frames_file, model_files, other_scene

_RESULTS = ("vpt.json", "mse.png", "strip.png", "prediction.gif")
_STRIP_FRAMES = 10  # frames shown in the strip, evenly spaced over the run
_GIF_SCALE = 4  # pixels per frame pixel in the GIF


def register(subparsers) -> None:
    """Add `keyvision evaluate`."""
    parser = add_command(
        subparsers,
        "evaluate",
        help="valid prediction time of a trained model on the validation runs",
        description="Predict every validation run of the frames from its first frames (keypoints and "
        "their central-difference velocity, integrated by the learnt dynamics with RK4 and projection, "
        "rendered) and score the valid prediction time (VPT, the paper's eq. 16: the first frame whose "
        "error exceeds that of the dataset's mean image, as a fraction of the run). Prints the mean, "
        "median and standard deviation over the runs; writes vpt.json, mse.png (the error over time, "
        "the paper's figure 3), strip.png (true frames over predicted ones, figure 4) and prediction.gif "
        "(true and predicted frames side by side, with the estimated and the predicted keypoints) to "
        "--out. Where the frames carry their ground truth, also the held-out R^2 of an affine map from "
        "the keypoints to the true pose (keyvision.keypoint_tracking).",
    )
    parser.add_argument("--model", required=True, help="the directory keyvision train wrote")
    parser.add_argument("--data", required=True, help="frames.npz, or the directory keyvision render wrote")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument(
        "--stage",
        default=None,
        help="evaluate the model as the training left it after this stage (autoencoder, dynamics, joint, "
        "refit, joint-2, ...; from the stages' files in --model) instead of the finished model",
    )
    parser.add_argument(
        "--batch", type=positive(integer=True), default=8, help="runs predicted per call (bounds the memory)"
    )
    parser.add_argument(
        "--strip-run",
        type=positive(integer=True, allow_zero=True),
        default=0,
        help="validation run in the strip",
    )
    add_overwrite(parser, "results")
    parser.set_defaults(run=run)


def _plot_mse(path, ts, mse, threshold: float) -> None:
    from cldyn._misc import atomic_save, optional_import

    plt = optional_import("matplotlib.pyplot", purpose="keyvision evaluate's plot")
    figure, axes = plt.subplots(figsize=(5, 3.2), layout="constrained")
    with warnings.catch_warnings():  # a frame that no run predicted (all failed) is a gap
        warnings.simplefilter("ignore", RuntimeWarning)
        axes.plot(ts, np.nanmean(mse, axis=0), label="mean over runs")
        low, high = np.nanpercentile(mse, 25, axis=0), np.nanpercentile(mse, 75, axis=0)
    axes.fill_between(ts, low, high, alpha=0.3, label="25-75%")
    axes.axhline(threshold, color="k", linestyle="--", linewidth=1, label="VPT threshold")
    axes.set(xlabel="time (s)", ylabel="MSE per frame", title="prediction error over time")
    axes.legend()
    atomic_save(path, lambda temporary: figure.savefig(temporary, dpi=120))
    plt.close(figure)


def _strip(path, truth, predicted) -> None:
    from cldyn._misc import atomic_save, optional_import

    imageio = optional_import("imageio.v3", purpose="keyvision evaluate's frame strip")
    shown = np.unique(
        np.linspace(0, truth.shape[0] - 1, min(_STRIP_FRAMES, truth.shape[0])).round().astype(int)
    )
    rows = [np.concatenate(list(frames[shown]), axis=1) for frames in (truth, predicted)]
    strip = np.round(255 * np.clip(np.nan_to_num(np.concatenate(rows, axis=0)), 0, 1)).astype(np.uint8)
    atomic_save(path, lambda temporary: imageio.imwrite(temporary, strip, extension=".png"))


def _gif(path, truth, predicted, estimated, predicted_keypoints, dt: float) -> None:
    """True frames with the estimated keypoints beside predicted frames with the predicted ones."""
    import keyvision
    from cldyn._misc import atomic_save, optional_import

    imageio = optional_import("imageio.v3", purpose="keyvision evaluate's GIF")
    pairs = [
        keyvision.draw_keypoints(np.repeat(np.repeat(frames, _GIF_SCALE, -3), _GIF_SCALE, -2), keypoints)
        for frames, keypoints in ((truth, estimated), (predicted, predicted_keypoints))
    ]
    movie = np.concatenate(pairs, axis=-2)
    atomic_save(
        path,
        lambda temporary: imageio.imwrite(temporary, movie, extension=".gif", duration=1000 * dt, loop=0),
    )


def _keypoint_error(validation, estimated) -> list[float]:
    """Per keypoint, the held-out RMS distance in pixels between the estimated keypoints and the true
    ones (MuJoCo's, through the camera) mapped by an affine map fitted by least squares on the first
    half of the frames (runs in order): how precisely the keypoints follow points of the bodies,
    wherever on them the estimator put them."""
    size = validation.image_size[0]
    count = estimated.shape[-1] // 2
    truth = validation.camera.to_image(validation.extras["keypoints"].reshape(-1, count, 2)).reshape(
        -1, 2 * count
    )
    estimated = estimated.reshape(-1, 2 * count)
    cut = max(1, truth.shape[0] // 2)
    design = np.concatenate([truth, np.ones((truth.shape[0], 1))], axis=1)
    solution, *_ = np.linalg.lstsq(design[:cut], estimated[:cut], rcond=None)
    residual = (estimated[cut:] - design[cut:] @ solution).reshape(-1, count, 2)
    return (np.sqrt(np.mean(np.sum(residual**2, axis=-1), axis=0)) * size / 2).tolist()


def _keypoint_motion(validation, estimated) -> list[float]:
    """Per keypoint, how far the estimated keypoint moves against the true one of its number: the
    RMS distance from its mean position over the frames, over the true keypoint's (MuJoCo's, through
    the camera). For a keypoint on a link turning about a pivot, its distance from the pivot over the
    true keypoint's (the shipped pendulum's: 0.36); near 0 for one that stands still, to which the
    affine fit of `_keypoint_error` is blind (a constant is an affine map of anything), as the
    constraint drift is (a still keypoint keeps every distance)."""
    count = estimated.shape[-1] // 2
    truth = validation.camera.to_image(validation.extras["keypoints"].reshape(-1, count, 2))
    estimated = estimated.reshape(-1, count, 2)

    def spread(points):
        return np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=-1), axis=0))

    return (spread(estimated) / np.maximum(spread(truth), 1e-12)).tolist()


def _constraint_drift(model, estimated, size: int) -> list[float] | None:
    """Per constraint of the dynamics, the RMS over runs of the standard deviation of its value along
    each run of estimated keypoints, in pixels: how far the keypoints are from rigid points of the
    bodies (0 when each pole keeps its length), from the frames alone, no ground truth needed."""
    constraint = getattr(model.dynamics, "constraint", None)
    if constraint is None:
        return None
    import jax

    values = np.asarray(jax.jit(jax.vmap(jax.vmap(constraint)))(estimated))  # (runs, frames, constraints)
    return (np.sqrt(np.mean(np.var(values, axis=1), axis=0)) * size / 2).tolist()


def report(model, validation, out, *, batch: int = 8, strip_run: int = 0) -> tuple[dict, str]:
    """Predict every run of `validation` (`keyvision.Frames`), score the VPT, write mse.png,
    strip.png and prediction.gif to `out`; returns the record for vpt.json and a summary line."""
    import keyvision

    from .._evaluate import decode_batch, encode_batch, json_number, predict_runs

    images = validation.images(np.float32)
    controls = validation.u.astype(np.float32)
    predicted_keypoints, predicted = predict_runs(model, images, controls, validation.dt, batch)
    estimated = np.concatenate(
        [np.asarray(encode_batch(model, images[i : i + batch])) for i in range(0, len(images), batch)]
    )
    # the autoencoder's ceiling: every frame drawn from its own estimated keypoints (perfect dynamics)
    redrawn = np.concatenate(
        [np.asarray(decode_batch(model, estimated[i : i + batch])) for i in range(0, len(images), batch)]
    )
    threshold = keyvision.prediction_threshold(images)
    vpt = np.asarray(keyvision.valid_prediction_time(predicted, images, threshold=threshold))
    ceiling = np.asarray(keyvision.valid_prediction_time(redrawn, images, threshold=threshold))
    mse = np.mean((predicted - images) ** 2, axis=(-3, -2, -1))  # NaN where a prediction failed
    failed = ~np.all(np.isfinite(predicted_keypoints), axis=(-2, -1))
    summary = {"mean": float(vpt.mean()), "median": float(np.median(vpt)), "std": float(vpt.std())}
    reconstruction = float(np.mean((redrawn - images) ** 2))
    record = {
        "vpt": summary,
        "vpt_per_run": vpt.tolist(),
        "autoencoder": {
            "vpt": {"mean": float(ceiling.mean()), "median": float(np.median(ceiling))},
            "mse": reconstruction,
            "mse_over_threshold": reconstruction / threshold,
        },
        "threshold": threshold,
        "mse_over_time": [json_number(v) for v in _over_runs(mse)],
        "mse_per_run": [[json_number(v) for v in run] for run in mse],
        "failed_runs": np.flatnonzero(failed).tolist(),
        "runs": validation.num_runs,
        "frames": validation.num_frames,
        "dt": validation.dt,
        "strip_run": strip_run,
    }
    if "qpos" in validation.extras:
        # the held-out R^2 of an affine map from the keypoints of the true frames to the true pose,
        # fitted on the first half of the frames (runs in order) and scored on the rest
        pose = keyvision.pose_features(validation)
        record["keypoint_tracking_r2"] = keyvision.keypoint_tracking(
            estimated.reshape(-1, estimated.shape[-1]), pose.reshape(-1, pose.shape[-1])
        )
    if "keypoints" in validation.extras and validation.extras["keypoints"].shape[-1] == estimated.shape[-1]:
        record["keypoint_error_px"] = _keypoint_error(validation, estimated)
        record["keypoint_motion"] = _keypoint_motion(validation, estimated)
    drift = _constraint_drift(model, estimated, validation.image_size[0])
    if drift is not None:
        record["constraint_drift_px"] = drift
    _plot_mse(out / "mse.png", validation.ts, mse, threshold)
    _strip(out / "strip.png", images[strip_run], predicted[strip_run])
    pick = (images, predicted, estimated, predicted_keypoints)
    _gif(out / "prediction.gif", *(a[strip_run] for a in pick), validation.dt)
    line = (
        f"VPT over {validation.num_runs} validation runs of {validation.num_frames} frames: mean "
        f"{summary['mean']:.3f}, median {summary['median']:.3f}, std {summary['std']:.3f} (threshold "
        f"{threshold:.4g}); autoencoder alone (frames redrawn from their own keypoints): VPT "
        f"{ceiling.mean():.3f}, MSE {reconstruction / threshold:.2f} of the threshold"
        + (
            f"; keypoint tracking R^2 {record['keypoint_tracking_r2']:.3f}"
            if "keypoint_tracking_r2" in record
            else ""
        )
        + "".join(
            f"; {label} " + ", ".join(f"{e:.2f}" for e in record[name]) + " px"
            for name, label in (
                ("keypoint_error_px", "keypoint error after an affine fit"),
                ("constraint_drift_px", "constraint drift along a run"),
            )
            if name in record
        )
        + (
            "; keypoint motion over the true keypoints' "
            + ", ".join(f"{m:.2f}" for m in record["keypoint_motion"])
            if "keypoint_motion" in record
            else ""
        )
        + (
            f"; the predictions of {failed.sum()} runs failed (a projection that did not converge: the "
            "model breaks its own constraints), their frames from the failure on scored as beyond the "
            "threshold"
            if failed.any()
            else ""
        )
        + f"; wrote {', '.join(_RESULTS)} to {out}"
    )
    return record, line


def _over_runs(mse):
    """The mean error at each time over the runs whose prediction reached it (NaN where none did)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(mse, axis=0)


def run(args: argparse.Namespace) -> int:
    """Load, predict, score, plot, print one line."""
    if args.stage is None:  # a stage's model is checked when it is rebuilt
        model_files(args.model, "--model")
    data_path = frames_file(args.data, "--data")
    out = output_directory(args.out, results=_RESULTS, overwrite=args.overwrite)
    from cldyn._misc import optional_import

    # the optional packages before the work, so a missing one fails at once
    optional_import("matplotlib", purpose="keyvision evaluate's plot")
    optional_import("imageio", purpose="keyvision evaluate's frame strip")
    import keyvision
    from cldyn._misc import atomic_write

    from ._common import load_model

    model, spec = load_model(args.model, "--model", args.stage)
    frames = keyvision.Frames.load(data_path)
    validation = frames.split()[1]
    if validation.num_runs == 0:
        raise CommandError(f"--data {data_path}: no validation runs")
    if args.strip_run >= validation.num_runs:
        raise CommandError(f"--strip-run {args.strip_run}: there are {validation.num_runs} validation runs")
    if validation.image_size != (model.image_size, model.image_size):
        raise CommandError(
            f"--data: frames of {validation.image_size} pixels; the model takes {model.image_size} "
            f"x {model.image_size}" + other_scene(frames, spec)
        )
    if validation.u.shape[-1] != spec["dynamics"]["num_inputs"]:
        raise CommandError(
            f"--data: {validation.u.shape[-1]} controls; the model takes {spec['dynamics']['num_inputs']}"
            + other_scene(frames, spec)
        )
    if validation.num_frames < 3:
        raise CommandError(f"--data: runs of {validation.num_frames} frames; a prediction starts from 3")
    record, line = report(model, validation, out, batch=args.batch, strip_run=args.strip_run)
    record.update(model=str(args.model), stage=args.stage, data=str(data_path))
    record.update(scene=frames.info.get("scene"))
    atomic_write(out / "vpt.json", json.dumps(record, indent=1))
    print(line)
    return 0
