"""`keyvision control`: swing a MuJoCo scene up with energy shaping on a model learnt from images,
the controller seeing only rendered camera frames (`keyvision.swing_up`).

The target is a frame (`--target target.png`, the model's image size) or, by default, the scene
rendered in its upright posture. With `--linearise`, MuJoCo's loop at the target under the same
controller, fed what it sees, is linearised too (`keyvision.target_linearisation`). Writes control.json
(success, errors, timing, and `true_loop`), target.png,
control.gif (the camera view of the first run with the estimated keypoints and the target's drawn)
and control.png (true joint angles, the learnt energy and the controls over time).
"""

import argparse
import json

from cldyn._cli._common import (
    CommandError,
    add_command,
    add_overwrite,
    input_file,
    output_directory,
    positive,
    seed,
)

from ._common import load_model, model_files

_RESULTS = ("control.json", "target.png", "control.gif", "control.png")
_GIF_SCALE = 4


def register(subparsers) -> None:
    """Add `keyvision control`."""
    parser = add_command(
        subparsers,
        "control",
        help="swing a scene up from camera frames with a learnt model (energy shaping)",
        description=__doc__,
    )
    parser.add_argument("--model", required=True, help="directory written by keyvision train")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--scene", help="the scene (default: the one the model was trained on)")
    parser.add_argument("--target", help="target frame, a PNG of the model's size (default: upright)")
    parser.add_argument(
        "--observe",
        choices=("frames", "state"),
        default="frames",
        help="what the controller sees: rendered frames, or the true state (for reference)",
    )
    parser.add_argument("--runs", type=positive(integer=True), default=1, help="runs from near hanging")
    parser.add_argument("--duration", type=positive(), default=10.0, help="seconds per run")
    parser.add_argument("--kp", type=positive(), default=5.0, help="stiffness of the shaped potential")
    parser.add_argument("--kd", type=positive(allow_zero=True), default=2.0, help="damping injection")
    parser.add_argument(
        "--metric",
        choices=("euclidean", "mass"),
        default="euclidean",
        help="the shaped potential's metric: euclidean (eq. 32, the paper) or mass (gains as rates, "
        "whatever the learnt Lagrangian's scale); see cldyn.EnergyShaping",
    )
    parser.add_argument(
        "--trim",
        action="store_true",
        help="subtract the controller's command at the target at rest (not part of eq. 32: for a target "
        "that is an equilibrium, it removes the rest offset of a learnt potential's error there)",
    )
    parser.add_argument(
        "--supersample",
        type=positive(integer=True),
        help="the camera's samples per pixel side (default: those of the frames the model was trained on; "
        "see keyvision.RenderProtocol)",
    )
    parser.add_argument("--tolerance", type=positive(), default=0.05, help="success radius in metres")
    parser.add_argument(
        "--linearise",
        action="store_true",
        help="also linearise MuJoCo's loop at the upright target under this controller, fed what it sees "
        "(keyvision.target_linearisation): whether the target can be held at all, and where the loop "
        "rests; written to control.json as true_loop",
    )
    parser.add_argument("--seed", type=seed, default=0, help="seed of the initial states")
    add_overwrite(parser, "results")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Load, swing up, write the results, print one line."""
    model_files(args.model, "--model")
    target_file = None if args.target is None else input_file(args.target, "--target")
    from cldyn._misc import optional_import

    imageio = optional_import("imageio.v3", purpose="keyvision control's GIF")
    optional_import("matplotlib", purpose="keyvision control's plot")
    import numpy as np

    import cldyn
    import keyvision
    from cldyn._misc import atomic_save, atomic_write
    from keyvision._files import trained_supersample

    model, spec = load_model(args.model, "--model")
    scene = args.scene or spec.get("data", {}).get("scene")
    if not scene:
        raise CommandError(f"--model {args.model}: its keyvision.json names no scene; pass --scene")
    target = None
    if target_file is not None:
        target = _target_frame(target_file, model.image_size, imageio)
    if not isinstance(model.dynamics, cldyn.ConstrainedLagrangian):
        raise CommandError(
            f"--model {args.model}: energy shaping needs a learnt potential and input matrix "
            f"(KeyCLD or KeyCLD-NC dynamics), this model's are {type(model.dynamics).__name__}"
        )
    out = output_directory(args.out, results=_RESULTS, overwrite=args.overwrite)
    # the controller and camera that the swing-up and the linearisation share
    controller = {
        "observe": args.observe,
        "kp": args.kp,
        "kd": args.kd,
        "metric": args.metric,
        "trim": args.trim,
        "supersample": args.supersample or trained_supersample(spec),
    }
    try:
        result = keyvision.swing_up(
            model,
            scene,
            target=target,
            runs=args.runs,
            duration=args.duration,
            tolerance=args.tolerance,
            seed=args.seed,
            progress_meter=cldyn.TqdmProgressMeter(),
            **controller,
        )
        loop = keyvision.target_linearisation(model, scene, **controller) if args.linearise else None
    except ValueError as error:
        raise CommandError(str(error)) from None
    atomic_save(
        out / "target.png",
        lambda temporary: imageio.imwrite(temporary, np.asarray(result["target_frame"]), extension=".png"),
    )
    _gif(out / "control.gif", result, imageio, atomic_save)
    _plot(out / "control.png", result, atomic_save)
    record = {
        key: result[key]
        for key in (
            "scene",
            "observe",
            "kp",
            "kd",
            "metric",
            "trim",
            "runs",
            "duration",
            "dt",
            "tolerance",
            "success_rate",
            "success",
            "final_error",
            "time_to_tolerance",
            "seconds",
            "steps_per_second",
            "real_time_rate",
        )
    }
    record.update(model=str(args.model), target=str(target_file) if target_file else "upright")
    record["target_keypoints"] = np.asarray(result["target_keypoints"]).tolist()
    if loop is not None:
        record["true_loop"] = loop
    atomic_write(out / "control.json", json.dumps(record, indent=1))
    reached = [t for t in result["time_to_tolerance"] if t is not None]
    print(
        f"swing-up of {scene} from {args.observe} with the model in {args.model}: "
        f"{sum(result['success'])} of {args.runs} runs within {args.tolerance} m of the target over the "
        f"last 0.5 s (final error {np.median(result['final_error']):.3f} m median"
        + (f", reached after {np.median(reached):.2f} s" if reached else "")
        + f"); {result['steps_per_second']:.0f} control steps/s, real time {result['real_time_rate']:.0f}; "
        f"wrote {', '.join(_RESULTS)} to {out}"
    )
    if loop is not None:
        held = "unstable: no run can hold it" if loop["largest_real_part"] > 0 else "stable"
        rest = "" if loop["largest_real_part"] > 0 else f", resting {loop['rest_error']:.3f} m from upright"
        gain = loop.get("camera_gain")
        seen = "" if gain is None else "; the camera reads " + ", ".join(f"{g:.0%}" for g in gain)
        print(
            f"the true loop at the target, fed the {args.observe}: largest real part "
            f"{loop['largest_real_part']:+.2f}/s ({held}){rest}"
            + ("" if gain is None else seen + " of a small turn of each joint near upright")
        )
    return 0


def _target_frame(path, size: int, imageio):
    """The target image as 8-bit RGB, as the renderer draws frames: 8- or 16-bit RGB or RGBA (alpha
    dropped); anything else (not an image, grey levels, another size) refused with what it is."""
    import numpy as np

    try:
        image = np.asarray(imageio.imread(path, plugin="pillow"))  # PNG, JPEG, ...: what Pillow reads
    except Exception as error:  # imageio raises many kinds for a file that is not an image
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise CommandError(f"--target {path}: not a readable image ({first})") from None
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        what = "grey levels" if image.ndim == 2 else f"an array of shape {image.shape}"
        raise CommandError(f"--target {path}: {what}; the model takes RGB frames of {size} x {size}")
    if image.shape[:2] != (size, size):
        raise CommandError(
            f"--target {path}: an image of {image.shape[:2]} pixels; the model takes {size} x {size}"
        )
    if image.dtype not in (np.uint8, np.uint16):
        raise CommandError(f"--target {path}: pixels of type {image.dtype}; 8- or 16-bit RGB expected")
    image = image[..., :3]
    return image if image.dtype == np.uint8 else np.round(image / 257.0).astype(np.uint8)


def _gif(path, result, imageio, atomic_save) -> None:
    """The first run's camera view, the estimated keypoints and the target's drawn on it (frames
    only: with `--observe state` the target frame with its keypoints)."""
    import numpy as np

    import keyvision

    frames = result["frames"][0] if result["frames"] else np.asarray(result["target_frame"])[None]
    big = np.repeat(np.repeat(frames, _GIF_SCALE, -3), _GIF_SCALE, -2)
    count = big.shape[0]
    target = np.broadcast_to(result["target_keypoints"], (count, result["target_keypoints"].shape[-1]))
    marked = keyvision.draw_keypoints(
        big, target, radius=2, colors=[(0.2, 1.0, 0.2)] * (target.shape[-1] // 2)
    )
    if result["frames"]:
        marked = keyvision.draw_keypoints(marked, result["x"][0, :count], radius=2)
    atomic_save(
        path,
        lambda temporary: imageio.imwrite(
            temporary, marked, extension=".gif", duration=1000 * result["dt"], loop=0
        ),
    )


def _plot(path, result, atomic_save) -> None:
    from cldyn._misc import optional_import

    plt = optional_import("matplotlib.pyplot", purpose="keyvision control's plot")
    ts = result["ts"]
    figure, axes = plt.subplots(4, 1, figsize=(6, 8), sharex=True, layout="constrained")
    for r in range(result["qpos"].shape[0]):
        axes[0].plot(ts, result["qpos"][r], linewidth=0.8)
        axes[1].plot(ts, result["errors"][r], linewidth=0.8)
        axes[2].plot(ts, result["energy"][r], linewidth=0.8)
        axes[3].plot(ts, result["u"][r], linewidth=0.8)
    axes[1].axhline(result["tolerance"], color="k", linestyle="--", linewidth=1)
    axes[0].set(ylabel="joint positions (MuJoCo)")
    axes[1].set(ylabel="keypoint error (m)", yscale="log")
    axes[2].set(ylabel="learnt energy")
    axes[3].set(ylabel="control", xlabel="time (s)")
    axes[0].set_title(f"swing-up from {result['observe']}: {result['success_rate']:.0%} of runs")
    atomic_save(path, lambda temporary: figure.savefig(temporary, dpi=110))
    plt.close(figure)
