"""`keyvision train`: a KeyCLD model learnt from rendered frames, in `keyvision.train`'s stages.

The output directory holds `keyvision.json` (the model's sizes, the dynamics' cldyn spec, the data, the
seed and the schedule; the frames' file, and with `--networks-from` that training's directory, recorded
relative to the output directory), `model.eqx` (the trained parameters: `keyvision evaluate --model`
reads both), and `keyvision.train`'s own files (`train.json`, and per stage `checkpoint-<stage>.eqx`,
`history-<stage>.json`, `model-<stage>.eqx`, and for the dynamics stages `keypoints-<stage>.npz`, the
keypoints they fit; with `--candidates`, `candidates.json`, the candidates' scores and the one chosen)
from which `--resume` continues.
"""

import argparse
import json
import os
import shlex
import sys

from cldyn._cli._common import (
    INTERRUPTED,
    CommandError,
    add_command,
    differences,
    output_directory,
    positive,
    refuse_existing,
    seed,
)
from cldyn._keycld import KEYCLD_SCENES, MODEL_KINDS

from .._assign import CHOICE_NAME
from .._files import INITIAL_NAME
from ._common import MODEL_NAME, SPEC_NAME, frames_file, relative_path

_STAGE_FILES = (("checkpoint", "eqx"), ("history", "json"), ("model", "eqx"), ("keypoints", "npz"))
_VALIDATION_RUNS = 4  # validated in one call at every checkpoint: a few runs suffice
_COLLOCATION_FRAMES = 5  # the collocation loss's central differences of central differences


def register(subparsers) -> None:
    """Add `keyvision train`."""
    from keyvision import Schedule
    from keyvision._train import NETWORKS_DYNAMICS_LR, PHYSICAL_DYNAMICS_LR

    default = Schedule()
    parser = add_command(
        subparsers,
        "train",
        help="learn a KeyCLD model from rendered frames",
        description="Train a KeyCLD model (keypoint estimator, cldyn dynamics, renderer) on the training "
        "runs of frames written by `keyvision render`, unsupervised, in four stages: the autoencoder on "
        "single frames, the dynamics on the frozen keypoints (collocation), everything jointly on windows "
        "of frames, then the dynamics again on the keypoints of the joint stage (multiple shooting). The "
        "dynamics get the constraints of the frames' KeyCLD scene. Writes "
        "keyvision.json and model.eqx (and the stages' checkpoints) to --out; prints a JSON summary.",
    )
    count, steps = positive(integer=True), positive(integer=True, allow_zero=True)
    parser.add_argument("--data", required=True, help="frames.npz, or the directory keyvision render wrote")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--model", choices=MODEL_KINDS, default="keycld", help="the dynamics model")
    parser.add_argument(
        "--constraint",
        choices=KEYCLD_SCENES,
        help="KeyCLD's constraints (default: the frames' KeyCLD scene; for another scene, its own "
        "constraints seen in the image, keyvision.scene_constraint)",
    )
    parser.add_argument("--width", type=count, default=32, help="width of both U-Nets (32 in the paper)")
    parser.add_argument(
        "--networks",
        choices=("unet", "fc"),
        default="unet",
        help="the estimator and renderer: the paper's U-Nets, or its FC ablation (appendix A.4)",
    )
    parser.add_argument(
        "--networks-from",
        metavar="DIR",
        default=None,
        help="start from the estimator and renderer of the autoencoder stage of another keyvision train "
        "on the same frames, with the same networks, and skip that stage here (the ablations of the "
        "dynamics share one autoencoder)",
    )
    parser.add_argument(
        "--dynamics-width",
        type=count,
        default=None,
        help="hidden width of the dynamics (default: 32; node2: 64)",
    )
    parser.add_argument(
        "--autoencoder-steps", type=steps, default=default.autoencoder_steps, help="stage (a)"
    )
    parser.add_argument(
        "--dynamics-steps",
        type=steps,
        default=default.dynamics_steps,
        help="steps of stage (b), the dynamics",
    )
    parser.add_argument(
        "--joint-steps", type=steps, default=default.joint_steps, help="steps of stage (c), joint"
    )
    parser.add_argument(
        "--refit-steps",
        type=steps,
        default=default.refit_steps,
        help="steps of stage (d), the dynamics again on the keypoints of stage (c) (multiple shooting)",
    )
    parser.add_argument(
        "--rounds",
        type=count,
        default=default.rounds,
        help="rounds of stages (c) and (d); the later joint stages train with multiple shooting",
    )
    parser.add_argument("--window", type=count, default=default.window, help="frames per window of stage (c)")
    parser.add_argument(
        "--lr", type=positive(), default=default.learning_rate, help="peak learning rate of stage (a)"
    )
    parser.add_argument(
        "--joint-lr",
        type=positive(),
        default=default.joint_learning_rate,
        help="peak learning rate of stage (c)",
    )
    parser.add_argument(
        "--dynamics-lr",
        type=positive(),
        default=None,
        help="peak learning rate of the dynamics stages (b) and (d) (default: "
        f"{NETWORKS_DYNAMICS_LR:g} for dynamics with networks; {PHYSICAL_DYNAMICS_LR:g} for dynamics "
        "without any, such as keycld-structured's, whose few physical parameters move slowly at the "
        "networks' rate)",
    )
    parser.add_argument(
        "--warmup-steps",
        type=positive(integer=True, allow_zero=True),
        default=default.warmup_steps,
        help="steps of linear learning-rate warm-up at the start of every stage",
    )
    parser.add_argument(
        "--autoencoder-batch",
        type=count,
        default=default.autoencoder_batch,
        help="frames per step of stage (a)",
    )
    parser.add_argument(
        "--joint-batch", type=count, default=default.joint_batch, help="windows per step of stage (c)"
    )
    parser.add_argument(
        "--candidates",
        type=count,
        default=default.candidates,
        help="initialise the networks this many times (from keys drawn from --seed), give each a trial of "
        "--candidate-steps steps of stage (a), and continue the one whose keypoints best keep the "
        "constraints (keyvision.constraint_score, no ground truth); 1 trains one initialisation",
    )
    parser.add_argument(
        "--candidate-steps",
        type=count,
        default=default.candidate_steps,
        help="steps of each candidate's trial (with --candidates above 1)",
    )
    parser.add_argument(
        "--candidate-runs",
        type=count,
        default=default.candidate_runs,
        help="score the candidates on at most this many training runs (every k-th run); more runs cost more "
        "encoding time",
    )
    parser.add_argument(
        "--rigid-steps",
        type=positive(integer=True, allow_zero=True),
        default=default.rigid_steps,
        help="steps of the rigid stage, between stage (a) and stage (b): the keypoints numbered after "
        "the constraints, then the networks trained further on single frames with the relative "
        "constraint drift added (asks each keypoint to sit where its constraints hold in every pose); "
        "0 leaves it out",
    )
    parser.add_argument(
        "--rigid-weight",
        type=positive(allow_zero=True),
        default=default.rigid_weight,
        help="weight of the relative constraint drift in the rigid stage",
    )
    parser.add_argument(
        "--dynamics-weight",
        type=positive(allow_zero=True),
        default=default.dynamics_weight,
        help="weight of the dynamics loss in stage (c), times h^4 (h the frame interval: a squared "
        "position, the same scale at any frame rate)",
    )
    parser.add_argument(
        "--refine-weight",
        type=positive(allow_zero=True),
        default=default.refine_weight,
        help="weight of the multiple-shooting loss in the joint stages of later rounds, times h^4",
    )
    parser.add_argument(
        "--heatmap-weight",
        type=positive(allow_zero=True),
        default=default.heatmap_weight,
        help="weight of the heatmap regulariser (0 leaves it out)",
    )
    parser.add_argument(
        "--constraint-weight",
        type=positive(allow_zero=True),
        default=default.constraint_weight,
        help="weight of the constraint drift (the variance of the keypoints' constraint values along "
        "each window) in the joint stages; 0 leaves it out",
    )
    parser.add_argument(
        "--constraint-drift",
        choices=("window", "pooled", "relative"),
        default=default.constraint_drift,
        help="the constraint drift's variance along each window, or pooled over the whole batch (the "
        "lengths are the same in every run: keeps a keypoint from sliding along its link with the pose), "
        "or pooled with each length's variance over its mean square (relative: scale-free)",
    )
    parser.add_argument(
        "--augment",
        action="store_true",
        help="show the estimator each frame turned and mirrored at random (dihedral augmentation)",
    )
    parser.add_argument("--seed", type=seed, default=0, help="seed of the model and the batches")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the training in --out (with the same options, or more --rounds to extend it)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="start afresh in an --out that holds a training"
    )
    parser.add_argument(
        "--loop",
        choices=("host", "compiled"),
        default="host",
        help="how the stages of images run their steps: one compiled step at a time (the faster on "
        "a CPU) or each chunk as one compiled loop (keyvision.train's loop; not part of the recipe)",
    )
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines")
    parser.set_defaults(run=run)


def _model_spec(args: argparse.Namespace, frames) -> dict:
    """The sizes of the model for these frames, checked before any training."""
    height, width = frames.image_size
    if height != width or height % 4:
        raise CommandError(
            f"--data: frames of {height}x{width} pixels; the U-Nets need square sides, multiples of 4"
        )
    if args.networks == "fc" and height % 16:
        raise CommandError(f"--networks fc: frames of {height} pixels; the FC networks need a multiple of 16")
    scene = str(frames.info.get("scene", ""))
    constraint = args.constraint or (scene.removeprefix("keycld/") if scene.startswith("keycld/") else None)
    if args.model.startswith("keycld") and constraint is None:
        if args.model == "keycld-structured":
            raise CommandError(
                f"--model keycld-structured: its joints are those of KeyCLD's scenes; the frames' scene "
                f"{scene!r} is not one (give --constraint, or --model keycld / keycld-coupled)"
            )
        import keyvision
        from cldyn._keycld import constraint_entries

        try:  # the scene's own pivots, rods and rails, seen in the image
            constraint = constraint_entries(keyvision.scene_constraint(frames))
        except ValueError as error:
            raise CommandError(
                f"the frames' scene {scene!r} is not a KeyCLD scene and its constraints cannot be read "
                f"({error}): give --constraint or --model nc / node2"
            ) from None
    if args.rigid_steps and not args.model.startswith("keycld"):
        raise CommandError(f"--rigid-steps: --model {args.model} has no constraints to keep rigid")
    if args.candidates > 1 and not args.model.startswith("keycld"):
        raise CommandError(f"--candidates: --model {args.model} has no constraints to choose by")
    if args.candidates > 1 and (args.networks_from is not None or not args.autoencoder_steps):
        raise CommandError(
            "--candidates: chooses among autoencoders, so it needs stage (a) (--autoencoder-steps, no "
            "--networks-from)"
        )
    node2 = args.model == "node2"
    keypoints = len(frames.info["keypoint_names"])
    networks = {} if args.networks == "unet" else {"networks": args.networks}  # older specs have no entry
    return {
        "schema": "keyvision.Model/1",
        "keypoints": keypoints,
        "image_size": height,
        "width": args.width,
        **networks,
        "dynamics": {
            "kind": args.model,
            "size": 2 * keypoints,
            "num_inputs": frames.u.shape[-1],
            "constraint": constraint if args.model.startswith("keycld") else None,
            "width": args.dynamics_width or (64 if node2 else 32),
            "depth": 3 if node2 else 2,
        },
        "dtype": "float32",
    }


def _check_frames(args: argparse.Namespace, frames) -> None:
    if args.joint_steps and args.window > frames.num_frames:
        raise CommandError(f"--window {args.window}: longer than the runs' {frames.num_frames} frames")
    if args.joint_steps and args.window < _COLLOCATION_FRAMES:
        raise CommandError(
            f"--window {args.window}: the collocation loss needs at least {_COLLOCATION_FRAMES}"
        )
    if (args.dynamics_steps or args.refit_steps) and frames.num_frames < _COLLOCATION_FRAMES:
        raise CommandError(
            f"--data: runs of {frames.num_frames} frames; the collocation loss needs at least "
            f"{_COLLOCATION_FRAMES}"
        )


def _stages(args: argparse.Namespace) -> list[str]:
    from keyvision._train import candidate_stages, stage_names

    later = (name for r in range(1, args.rounds + 1) for name in stage_names(r))
    return [*candidate_stages(args.candidates), "autoencoder", "rigid", "dynamics", *later]


def _networks_source(directory: str, spec: dict, frames) -> dict:
    """The estimator and renderer after the autoencoder stage of the training in `directory`, checked
    to fit this training (the same networks and sizes, the same frames), and what to record of them."""
    import pathlib

    from ._common import load_model

    model, source = load_model(directory, "--networks-from", stage="autoencoder")
    for name in ("keypoints", "width", "image_size", "networks"):
        if source.get(name, "unet" if name == "networks" else None) != spec.get(name, "unet"):
            raise CommandError(
                f"--networks-from {directory}: its {name} ({source.get(name, 'unet')}) differs from this "
                f"training's ({spec.get(name, 'unet')})"
            )
    if (source.get("data") or {}).get("cache_key") != frames.info.get("cache_key"):
        raise CommandError(f"--networks-from {directory}: it was trained on other frames than --data")
    seconds = None  # stage (a)'s, with the candidates' trials before it
    trials = sorted(pathlib.Path(directory).glob("history-candidate-*.json"))
    for history in [*trials, pathlib.Path(directory) / "history-autoencoder.json"]:
        try:
            records = json.loads(history.read_text())["records"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
            records = []
        if records and records[-1].get("seconds") is not None:
            seconds = (seconds or 0.0) + float(records[-1]["seconds"])
    return {
        "model": model,
        "record": {"directory": str(pathlib.Path(directory)), "autoencoder_seconds": seconds},
    }


def _more_rounds(previous, schedule: dict) -> bool:
    """Whether `schedule` is the `previous` one with at least as many rounds, and nothing else changed."""
    if not isinstance(previous, dict) or not isinstance(previous.get("rounds"), int):
        return False
    return previous["rounds"] <= schedule["rounds"] and {**previous, "rounds": schedule["rounds"]} == schedule


def _diverged(error, out) -> str:
    """What a stage that diverged leaves, and how to go on: the same options would diverge at the same
    step again, and `--resume` takes no other options, but a new training can start from the finished
    autoencoder stage."""
    models = sorted(out.glob("model-*.eqx"), key=lambda path: path.stat().st_mtime_ns)
    finished = [path.stem.removeprefix("model-") for path in models]
    said = str(error)
    if not finished:
        return said
    said += (
        f" The stages finished before it are kept in {out} ({', '.join(finished)}); `keyvision evaluate "
        f"--model {out} --stage {finished[-1]}` evaluates the last."
    )
    if "autoencoder" in finished:
        lower = "" if getattr(error, "before_any_update", False) else " (a lower --lr)"
        said += (
            f" To go on from its autoencoder with other options{lower}, start a new training "
            f"with --networks-from {out}."
        )
    return said


def _checkpointed(out, args: argparse.Namespace) -> bool:
    return any((out / f"checkpoint-{stage}.eqx").exists() for stage in _stages(args))


def _interrupted(args: argparse.Namespace, out) -> int:
    if _checkpointed(out, args):
        argv = [a for a in args.argv if a != "--overwrite"]
        argv += [] if "--resume" in argv else ["--resume"]
        where = "continue with:\n  " + shlex.join(["keyvision", *argv])
    else:
        where = "no checkpoint was written; nothing to resume"
    print(f"keyvision train: interrupted; {where}", file=sys.stderr)
    return INTERRUPTED


def run(args: argparse.Namespace) -> int:
    """Load the frames, build the model, train, save; print a JSON summary."""
    if args.resume and args.overwrite:
        raise CommandError("--resume continues the training in --out and --overwrite replaces it: give one")
    data_path = frames_file(args.data, "--data")
    out = output_directory(args.out)
    created = not out.exists()
    if not args.resume:
        refuse_existing(
            [out / name for name in (SPEC_NAME, MODEL_NAME, "train.json")]
            + [out / f"{name}-{stage}.{ext}" for stage in _stages(args) for name, ext in _STAGE_FILES],
            overwrite=args.overwrite,
            hint="pass --resume to continue that training or --overwrite to start afresh",
        )
    import dataclasses

    import equinox as eqx
    import jax

    import cldyn
    import keyvision
    from cldyn._misc import atomic_save, atomic_write
    from keyvision._train import for_dynamics

    frames = keyvision.Frames.load(data_path)
    spec = _model_spec(args, frames)
    _check_frames(args, frames)
    train_frames, validation_frames = frames.split()
    if train_frames.num_runs == 0:
        raise CommandError(f"--data {data_path}: all {frames.num_runs} runs are for validation")
    source = None if args.networks_from is None else _networks_source(args.networks_from, spec, frames)
    model_key, train_key = jax.random.split(jax.random.key(args.seed))
    try:
        model = keyvision.model_from_spec(spec, key=model_key)
    except ValueError as error:
        raise CommandError(f"--constraint {spec['dynamics']['constraint']}: {error}") from None
    # the first candidate is the model of --seed alone; the others fold their number into its key
    candidates = [model]
    for k in range(1, args.candidates):
        candidates.append(keyvision.model_from_spec(spec, key=jax.random.fold_in(model_key, k)))
    schedule = dataclasses.replace(
        keyvision.Schedule(),
        autoencoder_steps=0 if source is not None else args.autoencoder_steps,
        dynamics_steps=args.dynamics_steps,
        joint_steps=args.joint_steps,
        refit_steps=args.refit_steps,
        rounds=args.rounds,
        window=args.window,
        learning_rate=args.lr,
        joint_learning_rate=args.joint_lr,
        dynamics_learning_rate=args.dynamics_lr,
        warmup_steps=args.warmup_steps,
        autoencoder_batch=args.autoencoder_batch,
        candidates=args.candidates,
        candidate_steps=args.candidate_steps,
        candidate_runs=args.candidate_runs,
        rigid_steps=args.rigid_steps,
        rigid_weight=args.rigid_weight,
        joint_batch=args.joint_batch,
        dynamics_weight=args.dynamics_weight,
        refine_weight=args.refine_weight,
        heatmap_weight=args.heatmap_weight,
        constraint_weight=args.constraint_weight,
        constraint_drift=args.constraint_drift,
        augment=args.augment,
    )
    schedule = for_dynamics(schedule, model.dynamics)  # --dynamics-lr, or the default for --model
    spec.update(
        seed=args.seed,
        data={
            "file": relative_path(data_path, out),
            "scene": frames.info.get("scene"),
            "cache_key": frames.info.get("cache_key"),
            # the camera's samples per pixel side (keyvision.RenderProtocol): swing_up's default
            "supersample": int((frames.info.get("protocol") or {}).get("supersample", 1)),
        },
        schedule=schedule.describe(),
    )
    if source is not None:
        record = source["record"]
        spec["networks_from"] = {**record, "directory": relative_path(record["directory"], out)}
    spec_path = out / SPEC_NAME
    if args.resume and spec_path.is_file():
        try:
            previous = json.loads(spec_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise CommandError(
                f"{spec_path}: unreadable ({error}); cannot check what --resume continues"
            ) from None
        # paths recorded absolute by earlier versions compare as the relative ones recorded now
        for entry, name in (("data", "file"), ("networks_from", "directory")):
            recorded = previous.get(entry) if isinstance(previous.get(entry), dict) else {}
            if isinstance(recorded.get(name), str) and os.path.isabs(recorded[name]):
                previous[entry] = {**recorded, name: relative_path(recorded[name], out)}
        if isinstance(previous.get("schedule"), dict):  # a field added since: it held its default then
            defaults = for_dynamics(keyvision.Schedule(), model.dynamics).describe()
            previous["schedule"] = {**defaults, **previous["schedule"]}
        changed = sorted(name for name in {**previous, **spec} if previous.get(name) != spec.get(name))
        if changed == ["schedule"] and _more_rounds(previous["schedule"], spec["schedule"]):
            changed = []  # further rounds continue a training (finished or not): stages already run stay
        if changed:
            raise CommandError(
                f"--resume: the options differ from those of the training in {out} "
                f"({'; '.join(differences(previous, spec))}); "
                "resume with the same options or start afresh in another --out"
            )
    initial = out / INITIAL_NAME
    if source is not None:
        if args.resume and initial.is_file():  # the networks this training started from, as saved then
            model = eqx.tree_deserialise_leaves(initial, model)
        else:
            model = keyvision.KeyCLD(source["model"].estimator, model.dynamics, source["model"].renderer)
    validation = None
    if validation_frames.num_runs:
        validation = keyvision.ImageSequences.from_frames(
            validation_frames.select(slice(0, _VALIDATION_RUNS))
        )
    fresh = not spec_path.exists()
    atomic_write(spec_path, json.dumps(spec, indent=1))
    if source is not None and not (args.resume and initial.is_file()):
        atomic_save(initial, lambda temporary: eqx.tree_serialise_leaves(temporary, model))
    elif source is None and not args.resume:
        initial.unlink(missing_ok=True)  # an earlier training's, replaced by --overwrite
    if not args.resume:
        (out / CHOICE_NAME).unlink(missing_ok=True)
    try:
        result = keyvision.train(
            candidates if args.candidates > 1 else model,
            keyvision.ImageSequences.from_frames(train_frames),
            key=train_key,
            schedule=schedule,
            validation=validation,
            out=out,
            resume=args.resume,
            progress_meter=cldyn.TextProgressMeter() if args.progress else cldyn.NoProgressMeter(),
            loop=cldyn.CompiledLoop() if args.loop == "compiled" else cldyn.HostLoop(),
        )
    except BaseException as error:
        if fresh and not _checkpointed(out, args):
            for name in (SPEC_NAME, "train.json", INITIAL_NAME):  # nothing to resume: leave --out as it was
                (out / name).unlink(missing_ok=True)
            if created and not any(out.iterdir()):
                out.rmdir()
        if isinstance(error, KeyboardInterrupt):
            return _interrupted(args, out)
        if isinstance(error, cldyn.NonFiniteLossError):
            raise CommandError(_diverged(error, out)) from None
        raise
    atomic_save(out / MODEL_NAME, lambda temporary: eqx.tree_serialise_leaves(temporary, result.model))
    summary = {"out": str(out), "seconds": round(sum(s.seconds for s in result.stages.values()), 2)}
    for stage, fitted in result.stages.items():
        last = fitted.history[-1] if fitted.history else {}
        summary[stage] = {
            "steps": fitted.step,
            "loss": last.get("loss"),
            "validation": last.get("validation"),
        }
    if result.candidates is not None:
        record = result.candidates
        summary["candidates"] = {
            **dict(zip(record["stages"], record["scores"])),
            "chosen": record["chosen"],
            "runs": record.get("runs"),
        }
    print(json.dumps(summary))
    return 0
