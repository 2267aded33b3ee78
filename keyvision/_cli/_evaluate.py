"""`keyvision evaluate`: the valid prediction time of a trained model on the validation runs, the
error over time and a strip of true and predicted frames."""

import argparse
import json

import numpy as np

from cldyn._cli._common import CommandError, add_command, add_overwrite, output_directory, positive

from ._common import frames_file, model_files

_RESULTS = ("vpt.json", "mse.png", "strip.png")
_STRIP_FRAMES = 10  # frames shown in the strip, evenly spaced over the run


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
        "the paper's figure 3) and strip.png (true frames over predicted ones, figure 4) to --out.",
    )
    parser.add_argument("--model", required=True, help="the directory keyvision train wrote")
    parser.add_argument("--data", required=True, help="frames.npz, or the directory keyvision render wrote")
    parser.add_argument("--out", required=True, help="output directory")
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


def _predict(model, images, controls, dt: float, batch: int):
    """Every run predicted, `batch` runs per compiled call (the last call padded to the same shape)."""
    import equinox as eqx
    import jax

    import keyvision

    predict = eqx.filter_jit(jax.vmap(keyvision.predict, in_axes=(None, 0, 0, None)))
    runs = images.shape[0]
    batch = min(batch, runs)
    parts = []
    for start in range(0, runs, batch):
        z, u = images[start : start + batch], controls[start : start + batch]
        missing = batch - z.shape[0]
        if missing:
            z, u = (np.concatenate([a, np.repeat(a[-1:], missing, axis=0)]) for a in (z, u))
        parts.append(np.asarray(predict(model, z, u, dt))[: batch - missing])
    return np.concatenate(parts)


def _plot_mse(path, ts, mse, threshold: float) -> None:
    from cldyn._misc import atomic_save, optional_import

    plt = optional_import("matplotlib.pyplot", purpose="keyvision evaluate's plot")
    figure, axes = plt.subplots(figsize=(5, 3.2), layout="constrained")
    axes.plot(ts, mse.mean(axis=0), label="mean over runs")
    axes.fill_between(
        ts, np.percentile(mse, 25, axis=0), np.percentile(mse, 75, axis=0), alpha=0.3, label="25-75%"
    )
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
    strip = np.round(255 * np.clip(np.concatenate(rows, axis=0), 0, 1)).astype(np.uint8)
    atomic_save(path, lambda temporary: imageio.imwrite(temporary, strip, extension=".png"))


def run(args: argparse.Namespace) -> int:
    """Load, predict, score, plot, print one line."""
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

    model, spec = load_model(args.model, "--model")
    frames = keyvision.Frames.load(data_path)
    validation = frames.split()[1]
    if validation.num_runs == 0:
        raise CommandError(f"--data {data_path}: no validation runs")
    if args.strip_run >= validation.num_runs:
        raise CommandError(f"--strip-run {args.strip_run}: there are {validation.num_runs} validation runs")
    if validation.image_size != (model.image_size, model.image_size):
        raise CommandError(
            f"--data: frames of {validation.image_size} pixels; the model takes {model.image_size} "
            f"x {model.image_size}"
        )
    if validation.u.shape[-1] != spec["dynamics"]["num_inputs"]:
        raise CommandError(
            f"--data: {validation.u.shape[-1]} controls; the model takes {spec['dynamics']['num_inputs']}"
        )
    if validation.num_frames < 3:
        raise CommandError(f"--data: runs of {validation.num_frames} frames; a prediction starts from 3")
    images = validation.images(np.float32)
    controls = validation.u.astype(np.float32)
    predicted = _predict(model, images, controls, validation.dt, args.batch)
    threshold = keyvision.prediction_threshold(images)
    vpt = np.asarray(keyvision.valid_prediction_time(predicted, images, threshold=threshold))
    mse = np.mean((predicted - images) ** 2, axis=(-3, -2, -1))
    summary = {"mean": float(vpt.mean()), "median": float(np.median(vpt)), "std": float(vpt.std())}
    record = {
        "vpt": summary,
        "vpt_per_run": vpt.tolist(),
        "threshold": threshold,
        "mse_over_time": mse.mean(axis=0).tolist(),
        "runs": validation.num_runs,
        "frames": validation.num_frames,
        "dt": validation.dt,
        "model": str(args.model),
        "data": str(data_path),
        "scene": frames.info.get("scene"),
        "strip_run": args.strip_run,
    }
    atomic_write(out / "vpt.json", json.dumps(record, indent=1))
    _plot_mse(out / "mse.png", validation.ts, mse, threshold)
    _strip(out / "strip.png", images[args.strip_run], predicted[args.strip_run])
    print(
        f"VPT over {validation.num_runs} validation runs of {validation.num_frames} frames: mean "
        f"{summary['mean']:.3f}, median {summary['median']:.3f}, std {summary['std']:.3f} (threshold "
        f"{threshold:.4g}); wrote {', '.join(_RESULTS)} to {out}"
    )
    return 0
