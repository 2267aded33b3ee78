"""`keyvision distil`: a trained model's estimator taught its own reading averaged over the U-Net's
pooling phases (`keyvision.distil_shifts`), written as a new model directory."""

import argparse
import json
import pathlib

from cldyn._cli._common import (
    CommandError,
    add_command,
    add_overwrite,
    output_directory,
    positive,
    seed,
)

from .._files import MODEL_NAME, SPEC_NAME
from ._common import frames_file, relative_path


def register(subparsers) -> None:
    """Add `keyvision distil`."""
    parser = add_command(
        subparsers,
        "distil",
        help="teach a model's estimator its reading averaged over the U-Net's pooling phases",
        description="Read --runs training runs of --data (sampled by --seed; the frames' validation runs "
        "are left out) through the model's estimator shifted by 0-3 pixels each way (the 16 pooling phases "
        "of the U-Net), average the readings moved back by their shifts, and fine-tune the estimator so "
        "that one pass gives that average (keyvision.distil_shifts; no labels). The dynamics and the "
        "renderer are kept. Writes the model (keyvision.json, model.eqx) to --out, with the distillation's "
        "settings and figures under 'distilled' in keyvision.json.",
    )
    parser.add_argument("--model", required=True, help="the directory keyvision train wrote")
    parser.add_argument("--data", required=True, help="the model's training frames.npz, or its directory")
    parser.add_argument("--out", required=True, help="output directory (a new model directory)")
    parser.add_argument("--runs", type=positive(integer=True), default=200, help="training runs to read")
    parser.add_argument("--steps", type=positive(integer=True), default=2000, help="fine-tuning steps")
    parser.add_argument("--batch", type=positive(integer=True), default=32, help="frames per step")
    parser.add_argument("--lr", type=positive(), default=3e-4, help="peak learning rate")
    parser.add_argument("--seed", type=seed, default=0, help="seed of the runs read, the batches and shifts")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines")
    add_overwrite(parser, "a model")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Distil, save the model, print a summary line."""
    data_path = frames_file(args.data, "--data")
    out = output_directory(args.out, results=(SPEC_NAME, MODEL_NAME), overwrite=args.overwrite)
    import jax
    import numpy as np

    import cldyn
    import keyvision

    from ._common import model_and_frames

    model, spec, frames = model_and_frames(args.model, data_path)
    train, _ = frames.split()
    if not train.num_runs:
        raise CommandError(f"--data {data_path}: all {frames.num_runs} runs are for validation")
    rng = np.random.default_rng(args.seed)
    runs = np.sort(rng.choice(train.num_runs, min(args.runs, train.num_runs), replace=False))
    meter = cldyn.TextProgressMeter() if args.progress else cldyn.NoProgressMeter()
    distilled, report = keyvision.distil_shifts(
        model, train.frames[runs], key=jax.random.key(args.seed), steps=args.steps,
        batch_size=args.batch, learning_rate=args.lr, progress_meter=meter,
    )
    record = dict(spec)
    record["distilled"] = {
        "from": relative_path(args.model, out),
        "data": relative_path(data_path, out),
        "runs": len(runs), "steps": args.steps, "batch": args.batch, "learning_rate": args.lr,
        "seed": args.seed, **report,
    }
    if (spec.get("data") or {}).get("file"):  # the training data, relative to the new directory
        trained_on = pathlib.Path(args.model) / spec["data"]["file"]
        record["data"] = {**spec["data"], "file": relative_path(trained_on, out)}
    keyvision.save_model(out, distilled, record)
    print(
        json.dumps({"out": str(out), "rms_before": report["rms_before"], "rms_after": report["rms_after"]})
    )
    return 0
