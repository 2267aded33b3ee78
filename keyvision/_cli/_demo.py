"""`keyvision demo`: the image pipeline on an embedded default, with no arguments and no downloads.

A small KeyCLD model of the pendulum, trained from frames alone and shipped in the package
(`keyvision/demo/pendulum`, made by the commands in its `README.md`), sees the first three frames of
runs it was never trained on, rendered afresh by MuJoCo; its learnt dynamics predict the rest, its
renderer draws them, and the valid prediction time (VPT) scores them against the true frames.
"""

import argparse
import importlib.resources
import pathlib
import time

from cldyn._cli._common import CommandError, add_command, add_overwrite, output_directory, positive, seed

from ._evaluate import report

MODEL = "demo/pendulum"  # inside the keyvision package
SCENE = "keycld/pendulum"
# how the shipped model is made (its README.md says stage by stage); the demo names it when the model
# is missing from a checkout
RECIPE = (
    "keyvision render --scene keycld/pendulum --out runs/pendulum-data; "
    "keyvision train --data runs/pendulum-data --out keyvision/demo/pendulum --width 16 "
    "--autoencoder-steps 3000 --autoencoder-batch 16 --heatmap-weight 0 --joint-steps 600 --joint-batch 4 "
    "--rounds 2"
)
RESULTS = ("frames.npz", "vpt.json", "mse.png", "strip.png", "prediction.gif")


def model_directory() -> pathlib.Path:
    """The shipped demo model's directory."""
    return pathlib.Path(str(importlib.resources.files("keyvision").joinpath(MODEL)))


def register(subparsers) -> None:
    """Add `keyvision demo`."""
    parser = add_command(
        subparsers,
        "demo",
        help="predict new pendulum frames with the small KeyCLD model shipped in the package",
        description=__doc__,
    )
    parser.add_argument("--out", default="demo_output/keyvision", help="output directory")
    parser.add_argument("--runs", type=positive(integer=True), default=8, help="new runs to predict")
    parser.add_argument("--seed", type=seed, default=2026, help="seed of the new runs (not the training's)")
    add_overwrite(parser, "the frames and the results")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Load the model, render new runs, predict, score, write the strip and the GIF."""
    import json

    directory = model_directory()
    if not (directory / "model.eqx").is_file():
        raise CommandError(
            f"no demo model in {directory} (this checkout does not ship one yet); make it with: {RECIPE}"
        )
    out = output_directory(args.out, results=RESULTS, overwrite=args.overwrite)
    import cldyn
    import keyvision
    from cldyn._misc import atomic_write

    started = time.perf_counter()
    model, spec = keyvision.load_model(directory)
    trained = spec.get("data", {})
    print(
        f"[1/3] loaded the shipped KeyCLD model of {SCENE} ({spec['image_size']}x{spec['image_size']} "
        f"frames, U-Nets of width {spec['width']}; trained on {trained.get('runs', '?')} runs of seed "
        f"{trained.get('seed', '?')})"
    )
    protocol = keyvision.RenderProtocol(
        runs=args.runs, frames=50, image_size=spec["image_size"], validation_runs=args.runs
    )
    print(f"[2/3] rendering {args.runs} new runs x 50 frames with MuJoCo (seed {args.seed})")
    frames = keyvision.render(
        SCENE, protocol=protocol, seed=args.seed, cache=False, progress_meter=cldyn.TqdmProgressMeter()
    )
    frames.save(out / "frames.npz")
    print("[3/3] predicting each run from its first three frames (encode, integrate, render)")
    record, line = report(model, frames, out)
    record.update(model=str(directory), scene=SCENE, seed=args.seed)
    atomic_write(out / "vpt.json", json.dumps(record, indent=1))
    print(line)
    print(f"done in {time.perf_counter() - started:.0f} s")
    return 0
