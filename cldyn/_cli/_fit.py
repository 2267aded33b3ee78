"""`cldyn fit`: learn a KeyCLD model (or a baseline) from keypoint trajectories.

The output directory holds everything needed to use or continue the fit: `fit.json` (the model's
specification, the data, the options and seeds), `model.eqx` (the trained parameters),
`checkpoint.eqx` (for `--resume`) and `history.json`. `cldyn.load_fit(directory)` rebuilds the model.
"""

import argparse
import json
import os
import shlex
import sys

from .._keycld import KEYCLD_SCENES, MODEL_KINDS
from ._common import (
    INTERRUPTED,
    CommandError,
    add_command,
    differences,
    finite,
    input_file,
    output_directory,
    positive,
    refuse_existing,
    seed,
)

LOSSES = ("collocation", "rollout", "collocation+rollout", "inverse")
SPEC_NAME = "fit.json"  # what cldyn.load_fit reads
# Every file a fit leaves in --out (cldyn.fit's, without a stage, and fit.json).
FIT_FILES = (SPEC_NAME, "model.eqx", "checkpoint.eqx", "history.json", "history.csv")


def register(subparsers) -> None:
    """Add `cldyn fit`."""
    parser = add_command(
        subparsers,
        "fit",
        help="learn a KeyCLD model or a baseline from keypoint trajectories",
        description=(
            "Fit a KeyCLD model (point masses, MLP potential and input matrix, the scene's constraints), "
            "its structured variant (coupled masses, linear potential, joint motors), KeyCLD-NC (no "
            "constraint) or NODE2 (second-order neural ODE) to keypoint trajectories: a "
            "KeyCLD scene recorded with MuJoCo in the paper's protocol (--scene) or a file (--data: "
            "cldyn.Sequences.save or cldyn record). Writes fit.json, model.eqx, checkpoint.eqx and "
            "history.json to --out; prints a JSON summary."
        ),
    )
    count = positive(integer=True)
    source = parser.add_argument_group("data")
    source.add_argument("--data", help="a .npz written by Sequences.save or cldyn record")
    source.add_argument("--scene", choices=KEYCLD_SCENES, help="a KeyCLD scene")
    source.add_argument("--runs", type=count, default=500, help="runs to record for --scene")
    source.add_argument("--frames", type=count, default=50, help="frames per run for --scene")
    source.add_argument(
        "--noise", type=positive(allow_zero=True), default=0.0, help="keypoint noise (m) for --scene"
    )
    source.add_argument("--data-seed", type=seed, default=0, help="seed of the recorded data")
    source.add_argument(
        "--origin",
        type=finite,
        nargs=2,
        metavar=("X", "Y"),
        help="point subtracted from the keypoints (default: the pivot of a KeyCLD scene)",
    )
    source.add_argument(
        "--validation-runs",
        type=positive(integer=True, allow_zero=True),
        default=50,
        help="the last N runs validate (as in the paper; 0 for none)",
    )
    model = parser.add_argument_group("model")
    model.add_argument("--model", choices=MODEL_KINDS, default="keycld", help="the model")
    model.add_argument(
        "--constraint",
        choices=KEYCLD_SCENES,
        help="KeyCLD's constraints for this system (default: from the scene)",
    )
    model.add_argument("--width", type=count, help="hidden width (default: 32; NODE2: 64)")
    model.add_argument("--depth", type=count, help="hidden layers (default: 2; NODE2: 3)")
    training = parser.add_argument_group("training")
    training.add_argument("--out", required=True, help="output directory")
    training.add_argument("--loss", choices=LOSSES, default="collocation", help="the loss")
    training.add_argument("--steps", type=count, default=5000, help="optimiser steps")
    training.add_argument("--batch-size", type=count, default=32, help="runs per step")
    training.add_argument("--lr", type=positive(), default=3e-3, help="peak learning rate")
    training.add_argument("--clip", type=positive(), default=5.0, help="element-wise gradient clipping")
    training.add_argument("--seed", type=seed, default=0, help="seed of the model and the batches")
    training.add_argument(
        "--resume",
        action="store_true",
        help="continue the fit in --out from its checkpoint.eqx (the options must be those it was started "
        "with)",
    )
    training.add_argument(
        "--force",
        action="store_true",
        help="with --resume: continue although options differ from --out/fit.json (the earlier settings "
        "are kept in fit.json under 'previous')",
    )
    training.add_argument(
        "--overwrite",
        action="store_true",
        help="start afresh in an --out that holds a fit; its model stays loadable until this one ends",
    )
    training.add_argument("--validate-every", type=count, default=250, help="steps between validations")
    training.add_argument("--checkpoint-every", type=count, default=500, help="steps between checkpoints")
    training.add_argument("--history", choices=("json", "csv"), default="json", help="history format")
    training.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    parser.set_defaults(run=run)


def _data(args: argparse.Namespace):
    """`(Sequences, description for fit.json, KeyCLD scene or None)` from `--data` or `--scene`."""
    import cldyn

    if args.scene is not None:
        from cldyn.mujoco import keycld_dataset

        data = keycld_dataset(
            args.scene,
            runs=args.runs,
            frames=args.frames,
            noise=args.noise,
            seed=args.data_seed,
            progress_meter=_meter(args),
        )
        description = {
            "scene": args.scene,
            "runs": args.runs,
            "frames": args.frames,
            "noise": args.noise,
            "seed": args.data_seed,
        }
        return data, description, args.scene
    path = input_file(args.data, "--data")
    data = cldyn.Sequences.load(path)
    description, scene, origin = {"file": str(path)}, None, args.origin
    mjcf = data.info.get("mjcf")
    if isinstance(mjcf, str):  # recorded from MuJoCo
        description.update(mjcf=mjcf, seed=data.info.get("seed"))
        if mjcf.startswith("keycld/"):
            scene = mjcf.removeprefix("keycld/")
            if origin is None:
                from cldyn.mujoco import keycld_origin

                origin = keycld_origin(scene)
    if origin is not None:
        data = data.relative_to(origin)
    return data, description, scene


def _check_kinematics(args: argparse.Namespace, model, data, scene) -> None:
    """Refuse keypoints that break the model's constraints by more than their noise (a pivot away from
    the origin the constraints assume, say): training would fit a mechanism that is not there."""
    import cldyn

    constraint = getattr(model, "constraint", None)
    if constraint is None:
        return
    try:
        cldyn.check_constraints(
            constraint,
            data.x,
            noise=cldyn.estimate_noise(data.x),
            keypoint_names=data.info.get("keypoint_names"),
            what=f"the {scene} model",
        )
    except cldyn.ConstraintViolation as error:
        where = "--origin X Y (the pivot's position)" if args.origin is None else "another --origin"
        raise CommandError(
            f"the data do not fit --constraint {scene}: {error}. If the mechanism's fixed point is not at "
            f"the origin, pass {where}"
        ) from None


def _meter(args: argparse.Namespace):
    import cldyn

    return cldyn.TqdmProgressMeter() if args.progress else cldyn.NoProgressMeter()


def _loss(name: str):
    import cldyn

    return {
        "collocation": lambda: cldyn.Collocation(),
        "rollout": lambda: cldyn.Rollout(steps=4),
        "collocation+rollout": lambda: cldyn.Collocation() + cldyn.Rollout(steps=4),
        "inverse": lambda: cldyn.InverseDynamics(),
    }[name]()


def _check_options(args: argparse.Namespace) -> None:
    """The checks that need no data: before anything is loaded or recorded."""
    if (args.data is None) == (args.scene is None):
        raise CommandError("give exactly one of --data FILE and --scene NAME")
    if args.force and not args.resume:
        raise CommandError("--force only applies with --resume")
    if args.resume and args.overwrite:
        raise CommandError("--resume continues the fit in --out and --overwrite replaces it: give one")
    if args.scene is not None:
        _check_runs(args, args.runs)


def _check_runs(args: argparse.Namespace, runs: int) -> None:
    if args.validation_runs >= runs:
        raise CommandError(
            f"--validation-runs {args.validation_runs}: must be fewer than the {runs} runs of the data"
        )
    if args.batch_size > runs - args.validation_runs:
        raise CommandError(
            f"--batch-size {args.batch_size}: larger than the {runs - args.validation_runs} training runs "
            f"({runs} runs, {args.validation_runs} for validation)"
        )


def _previous_spec(args: argparse.Namespace, path) -> dict | None:
    """The settings of the fit being resumed, from its fit.json (None if it has none)."""
    if not (args.resume and path.is_file()):
        return None
    try:
        previous = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CommandError(f"{path}: unreadable ({error}); cannot check what --resume continues") from None
    if not isinstance(previous, dict):
        raise CommandError(f"{path}: not a fit's settings; cannot check what --resume continues")
    return previous


def _resume_command(args: argparse.Namespace, *, force: bool) -> str:
    argv = [a for a in args.argv if a != "--overwrite"]
    argv += [flag for flag in ("--resume",) + (("--force",) if force else ()) if flag not in argv]
    return shlex.join(["cldyn"] + argv)


def _interrupted(args: argparse.Namespace, out, *, spec_current: bool) -> int:
    """Say where the last checkpoint is and how to continue from it."""
    from .._checkpoint import CheckpointError, read_header

    checkpoint = out / "checkpoint.eqx"
    try:
        step = read_header(checkpoint)[0].get("step")
    except CheckpointError:
        step = None
    if step is None:
        where = "no checkpoint was written; nothing to resume"
    else:
        # fit.json still describes the earlier fit (kept loadable) when this one replaces or changes it
        where = (
            f"the last checkpoint is {checkpoint} (step {step} of {args.steps}); continue with:\n  "
            + _resume_command(args, force=not spec_current)
        )
    print(f"cldyn fit: interrupted; {where}", file=sys.stderr)
    return INTERRUPTED


def run(args: argparse.Namespace) -> int:
    """Load or record the data, build the model, fit, write fit.json, print a JSON summary."""
    _check_options(args)
    out = output_directory(args.out)
    created = not out.exists()
    if not args.resume:
        refuse_existing(
            [out / name for name in FIT_FILES],
            overwrite=args.overwrite,
            hint="pass --resume to continue that fit or --overwrite to start afresh",
        )
    path = out / SPEC_NAME
    previous = _previous_spec(args, path)
    import jax
    import jax.numpy as jnp
    import optax

    import cldyn

    from .._misc import atomic_write

    data, description, scene = _data(args)
    constraint = args.constraint or scene
    _check_runs(args, data.num_runs)
    train, validation = (
        (data, None) if args.validation_runs == 0 else data.split(data.num_runs - args.validation_runs)
    )
    node2 = args.model == "node2"
    model_spec = {
        "kind": args.model,
        "size": data.size,
        "num_inputs": data.num_inputs,
        "constraint": None if args.model in ("nc", "node2") else constraint,
        "width": args.width or (64 if node2 else 32),
        "depth": args.depth or (3 if node2 else 2),
    }
    model_key, fit_key = jax.random.split(jax.random.key(args.seed))
    try:
        model = cldyn.model_from_spec(model_spec, key=model_key)
    except ValueError as error:
        if model_spec["constraint"] is None:
            raise
        raise CommandError(f"--constraint {model_spec['constraint']}: {error}") from None
    _check_kinematics(args, model, data, model_spec["constraint"])
    schedule = optax.cosine_decay_schedule(args.lr, args.steps, alpha=0.01)
    optimizer = optax.chain(optax.clip(args.clip), optax.adam(schedule))
    spec = {
        "model": model_spec,
        "data": description,
        "dt": data.dt,
        "loss": args.loss,
        "steps": args.steps,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "clip": args.clip,
        "schedule": "cosine to 1%",
        "seed": args.seed,
        "validation_runs": args.validation_runs,
        "dtype": "float32",
    }
    changed = [] if previous is None else differences(previous, json.loads(json.dumps(spec)))
    if changed and not args.force:
        raise CommandError(
            f"--resume: the options differ from those of the fit in {path} ({'; '.join(changed)}); "
            "resume with the same options, add --force to continue with these, or start afresh in "
            "another --out"
        )
    if changed:
        spec["previous"] = previous
    # fit.json is written before training only where it describes no earlier model: an earlier fit
    # (replaced by --overwrite or changed by --force) stays loadable until this one has finished.
    fresh = not path.exists()
    if fresh:
        atomic_write(path, json.dumps(spec, indent=1))
    try:
        result = cldyn.fit(
            model,
            train,
            loss=_loss(args.loss),
            steps=args.steps,
            key=fit_key,
            optimizer=optimizer,
            batching=cldyn.Runs(args.batch_size),
            validation=validation,
            validate_every=args.validate_every,
            out=out,
            checkpoint_every=args.checkpoint_every,
            resume=args.resume,
            force=args.force,
            history_format=args.history,
            dtype=jnp.float32,
            progress_meter=_meter(args),
        )
    except BaseException as error:
        if fresh and not (out / "checkpoint.eqx").exists():
            os.unlink(path)  # nothing to resume: leave the directory as it was
            if created and not any(out.iterdir()):
                out.rmdir()
        if isinstance(error, KeyboardInterrupt):
            return _interrupted(args, out, spec_current=fresh or not (changed or args.overwrite))
        raise
    if not fresh and (changed or args.overwrite):
        atomic_write(path, json.dumps(spec, indent=1))
    last = result.history[-1] if result.history else {}
    summary = {
        "out": str(out),
        "model": args.model,
        "steps": result.step,
        "seconds": round(result.seconds, 2),
        "loss": last.get("loss"),
        "validation": last.get("validation"),
    }
    print(json.dumps(summary))
    return 0
