"""`keyvision identify`: what a model learnt from images is missing, found in frames of the system."""

import argparse
import json

from cldyn._cli._common import (
    CommandError,
    add_command,
    add_overwrite,
    enable_float64,
    output_directory,
    positive,
    seed,
)
from cldyn._cli._identify import REPORT_FILES, add_effects_option

from ._common import frames_file, other_scene

# what cldyn's Identification.save writes, and the effects in MuJoCo's units
_RESULTS = (*REPORT_FILES, "effects.json", "image_error.png")


def register(subparsers) -> None:
    """Add `keyvision identify`."""
    parser = add_command(
        subparsers,
        "identify",
        help="find the physics a model learnt from images is missing, in frames of the system",
        description="Encode every frame of --data with the model's estimator, read the joints of the "
        "keypoints from the model's constraints (hinges and slides, named after the scene's MuJoCo "
        "joints; from the scene itself where its constraints fix their geometry, as a slide on a turning "
        "body), run cldyn's identify with the learnt dynamics as the nominal model (float64), and "
        "convert the detected effects to MuJoCo's units with the camera's scale and the energy scale "
        "that the scene's actuator gears fix. Writes cldyn's report (report.json, report.md, plots) and "
        "effects.json (every detection in MuJoCo's units and the model's, and the energy balance's missing "
        "damping at each joint) to --out.",
    )
    parser.add_argument("--model", required=True, help="the directory keyvision train wrote")
    parser.add_argument("--data", required=True, help="frames.npz of the system, or the directory of one")
    parser.add_argument("--out", required=True, help="output directory")
    add_effects_option(parser)
    parser.add_argument("--seed", type=seed, default=0, help="seed of the hold-out split and the bootstrap")
    parser.add_argument(
        "--refine-steps",
        type=positive(integer=True, allow_zero=True),
        default=0,
        help="after the effects are added, train the model this many steps jointly with the image losses "
        "on the identified runs (the joint stage of the model's own training recipe); 0: no such stage",
    )
    parser.add_argument(
        "--add-balance",
        action="store_true",
        help="also add to the model the damping that the energy balance finds at a joint (interval above "
        "zero) where identify detected none (cldyn.energy_balance; see keyvision.identify's add_balance)",
    )
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines")
    add_overwrite(parser, "results")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Identify, save the reports, print a summary line."""
    data_path = frames_file(args.data, "--data")
    out = output_directory(args.out, results=_RESULTS, overwrite=args.overwrite)
    enable_float64()
    import cldyn
    import keyvision
    from cldyn._misc import atomic_write

    from ._common import model_and_frames

    model, spec, frames = model_and_frames(args.model, data_path)
    # the model's inputs are the actuators of the scene it was trained on: the frames' controls are
    # placed by name (a scene may drive fewer joints, as dm_control's stock acrobot does)
    inputs = None
    trained_on = (spec.get("data") or {}).get("scene")
    if trained_on and frames.info.get("actuator_names"):
        try:
            inputs = keyvision.scene_actuators(trained_on)
        except (ValueError, FileNotFoundError):
            inputs = None  # a scene no longer at hand: the controls must then match in number
        if inputs is not None and len(inputs) != spec["dynamics"]["num_inputs"]:
            inputs = None
    if inputs is None and frames.u.shape[-1] != spec["dynamics"]["num_inputs"]:
        raise CommandError(
            f"--data: {frames.u.shape[-1]} controls; the model takes {spec['dynamics']['num_inputs']}"
            + other_scene(frames, spec)
        )
    meter = cldyn.TextProgressMeter() if args.progress else None
    refine = None
    if args.refine_steps:  # the joint stage of the model's own recipe (keyvision.json)
        from keyvision._identify import joint_stage

        refine = joint_stage(spec.get("schedule") or {}, args.refine_steps)
    try:
        result = keyvision.identify(
            model,
            frames,
            inputs=inputs,
            refine=refine,
            add_balance=args.add_balance,
            progress_meter=meter,
            effects=args.effects,
            seed=args.seed,
        )
    except (ValueError, TypeError, cldyn.ConstraintViolation) as error:
        raise CommandError(str(error)) from None
    result.identification.save(out)
    record = {
        "model": str(args.model),
        "data": str(data_path),
        "outcome": result.identification.outcome,
        "effects": list(result.effects),
        "joints": dict(zip(result.structure.names, result.structure.kinds)),
        "joules_per_unit": result.joules_per_unit,
        "metres_per_unit": result.metres_per_unit,
        "energy_spread": result.energy_spread,
        "images": result.images,
        "energy_balance": list(result.balance),
    }
    atomic_write(out / "effects.json", json.dumps(record, indent=1))
    if result.images is not None:
        _plot_image_error(out / "image_error.png", result.images)

    def listed(source):
        return "; ".join(
            f"{e['name']}[{e['where']}]" + ("" if e["value"] is None else f" = {e['value']:.4g}")
            for e in result.effects
            if e["source"] == source
        )

    found, added = listed("force residual"), listed("energy balance")
    if added:
        found += f"{'; ' if found else ''}added from the energy balance: {added}"
    before, after = result.identification.before, result.identification.after
    images = ""
    if result.images is not None:
        was, now = result.images["before"], result.images["after"]
        images = (
            f"; on {result.images['runs']} validation runs VPT {was['vpt']['mean']:.3f} -> "
            f"{now['vpt']['mean']:.3f}, image MSE {_mse(was)} -> {_mse(now)}"
        )
        if "refined" in result.images:
            refined = result.images["refined"]
            images += (
                f" (refined with the image losses: VPT {refined['vpt']['mean']:.3f}, MSE {_mse(refined)})"
            )
    balance = "; ".join(
        f"{b['where']} {b['value']:.3g} [{b['ci'][0]:.3g}, {b['ci'][1]:.3g}]" for b in result.balance
    )
    if balance:
        images += f"; the energy balance's missing damping: {balance} (MuJoCo's units)"
    print(
        f"{result.identification.outcome}{': ' + found if found else ''} (MuJoCo's units); held-out rollout "
        f"error over 1 s {before.rollout_rmse_1s:.4g} -> {after.rollout_rmse_1s:.4g} (image units){images}; "
        f"wrote {', '.join(_RESULTS)} to {out}"
    )
    return 0


def _plot_image_error(path, images: dict) -> None:
    """The held-out runs' image MSE frame by frame, before and after (and refined), with the VPT
    threshold."""
    import numpy as np

    from cldyn._misc import atomic_save, optional_import

    plt = optional_import("matplotlib.pyplot", purpose="keyvision identify's plot")
    figure, axes = plt.subplots(figsize=(5, 3.2), layout="constrained")
    for name in ("before", "after", "refined"):
        if name in images:
            mse = np.asarray(images[name]["mse_over_time"], dtype=float)  # null: a failed prediction
            label = f"{name}: VPT {images[name]['vpt']['mean']:.2f}"
            axes.plot(images["dt"] * np.arange(mse.size), mse, label=label)
    axes.axhline(images["threshold"], color="k", linestyle="--", linewidth=1, label="VPT threshold")
    axes.set(
        xlabel="time (s)",
        ylabel="image MSE (mean over runs)",
        yscale="log",
        title=f"{images['runs']} held-out runs",
    )
    axes.legend(fontsize=8)
    atomic_save(path, lambda temporary: figure.savefig(temporary, dpi=120))
    plt.close(figure)


def _mse(images: dict) -> str:
    """An image MSE for the summary line; a model with failed predictions has none (their runs named)."""
    if images["mse"] is not None:
        return f"{images['mse']:.3g}"
    return f"none (the predictions of runs {images['failed_runs']} failed)"
