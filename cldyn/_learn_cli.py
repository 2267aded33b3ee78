"""`cldyn fit`: learn a KeyCLD model (or a baseline) from keypoint trajectories on the command line.

The output directory holds everything needed to use or continue the fit: `fit.json` (the model's
specification, the data, the options and seeds), `model.eqx` (the trained parameters),
`checkpoint.eqx` (for `--resume`) and `history.json`. `load_fitted(directory)` rebuilds the model.
"""

import argparse
import json
import pathlib
import zipfile

import numpy as np

MODELS = ("keycld", "keycld-coupled", "nc", "node2")
LOSSES = ("collocation", "rollout", "collocation+rollout", "inverse")
SPEC_NAME = "fit.json"


def build_model(spec: dict, key):
    """The untrained model that `spec` (the `model` entry of `fit.json`) describes."""
    from ._baselines import SecondOrderNeuralODE
    from ._keycld import keycld_constraint, keycld_model

    kind, size, inputs = spec["kind"], int(spec["size"]), int(spec["num_inputs"])
    if kind not in MODELS:
        raise ValueError(f"unknown model {kind!r}; choose one of {', '.join(MODELS)}")
    if kind == "node2":
        return SecondOrderNeuralODE(size, inputs, width=spec["width"], depth=spec["depth"], key=key)
    constraint = None
    if kind != "nc":
        if spec.get("constraint") in (None, "none"):
            raise ValueError("KeyCLD needs a constraint: pass --constraint pendulum|cartpole|acrobot")
        constraint = keycld_constraint(spec["constraint"])
    mass = "coupled" if kind == "keycld-coupled" else "point"
    return keycld_model(
        size, inputs, constraint, key=key, width=spec["width"], depth=spec["depth"], mass=mass
    )


def load_fitted(directory):
    """The trained model in a `cldyn fit` output directory (float32, as trained).

    **Arguments:**

    - `directory`: the `--out` directory of `cldyn fit`.

    **Returns:** `(model, spec)` with the model and the parsed `fit.json`.
    """
    import equinox as eqx
    import jax

    from ._learn import MODEL_NAME, _cast

    directory = pathlib.Path(directory)
    path = directory / SPEC_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not a cldyn fit directory (no {SPEC_NAME})")
    spec = json.loads(path.read_text())
    like = _cast(build_model(spec["model"], jax.random.key(spec["seed"])), spec.get("dtype"))
    try:
        model = eqx.tree_deserialise_leaves(directory / MODEL_NAME, like)
    except Exception as error:  # a missing, truncated or mismatched file
        raise ValueError(f"{directory / MODEL_NAME}: cannot load the trained model ({error})") from error
    return model, spec


def _file_schema(path: pathlib.Path) -> str:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return json.loads(str(npz["metadata"])).get("schema", "")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise ValueError(f"{path}: not a readable Sequences or Recording .npz file ({error})") from error


def _load_data(args) -> tuple:
    """`(Sequences, description, constraint name or None)` from `--data` or `--scene`."""
    from ._learn import _SEQUENCES_SCHEMA, Sequences

    origin = None if args.origin is None else np.asarray(args.origin, dtype=float)
    if args.scene is not None:
        from .mujoco import keycld_dataset

        data = keycld_dataset(
            args.scene, runs=args.runs, frames=args.frames, noise=args.noise, seed=args.data_seed,
            progress=args.progress,
        )
        description = {
            "scene": args.scene, "runs": args.runs, "frames": args.frames, "noise": args.noise,
            "seed": args.data_seed,
        }
        return data, description, args.scene
    path = pathlib.Path(args.data)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such data file")
    schema = _file_schema(path)
    if schema == _SEQUENCES_SCHEMA:
        data = Sequences.load(path)
        if origin is not None:
            data = Sequences(
                data.x - np.tile(origin, data.size // origin.shape[0]), data.u, data.dt,
                xd=data.xd, xdd=data.xdd,
            )
        return data, {"file": str(path)}, None
    from .mujoco import Recording, keycld_origin

    recording = Recording.load(path)
    scene = None
    if recording.mjcf.startswith("keycld/"):
        scene = recording.mjcf.removeprefix("keycld/")
        if origin is None:
            origin = keycld_origin(scene)
    data = Sequences.from_recording(recording, origin=origin)
    return data, {"file": str(path), "mjcf": recording.mjcf, "seed": recording.seed}, scene


def _loss(name: str):
    from ._learn import Collocation, InverseDynamics, Rollout

    return {
        "collocation": Collocation(),
        "rollout": Rollout(steps=4),
        "collocation+rollout": Collocation() + Rollout(steps=4),
        "inverse": InverseDynamics(),
    }[name]


def _fit(args: argparse.Namespace) -> int:
    import jax
    import jax.numpy as jnp
    import optax

    from ._learn import fit

    if (args.data is None) == (args.scene is None):
        raise ValueError("give exactly one of --data FILE and --scene NAME")
    data, description, scene = _load_data(args)
    constraint = args.constraint or scene
    if args.validation_runs >= data.num_runs:
        raise ValueError(f"--validation-runs {args.validation_runs}: only {data.num_runs} runs in the data")
    train, validation = (
        (data, None) if args.validation_runs == 0 else data.split(data.num_runs - args.validation_runs)
    )
    width, depth = args.width, args.depth
    if width is None:
        width = 64 if args.model == "node2" else 32
    if depth is None:
        depth = 3 if args.model == "node2" else 2
    model_spec = {
        "kind": args.model, "size": data.size, "num_inputs": data.num_inputs,
        "constraint": None if args.model in ("nc", "node2") else constraint,
        "width": width, "depth": depth,
    }
    model_key, fit_key = jax.random.split(jax.random.key(args.seed))
    model = build_model(model_spec, model_key)
    schedule = optax.cosine_decay_schedule(args.lr, max(args.steps, 1), alpha=0.01)
    optimizer = optax.chain(optax.clip(args.clip), optax.adam(schedule))
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = {
        "model": model_spec, "data": description, "dt": data.dt, "loss": args.loss, "steps": args.steps,
        "batch_size": args.batch_size, "lr": args.lr, "clip": args.clip, "schedule": "cosine to 1%",
        "seed": args.seed, "validation_runs": args.validation_runs, "dtype": "float32",
    }
    path = out / SPEC_NAME
    if args.resume and path.is_file():
        previous = json.loads(path.read_text())
        if previous.get("model") != model_spec or previous.get("seed") != args.seed:
            raise ValueError(f"{path}: --resume with a different model or seed than the fit in {out}")
    path.write_text(json.dumps(spec, indent=1))
    result = fit(
        model, train, loss=_loss(args.loss), steps=args.steps, key=fit_key, optimizer=optimizer,
        batch_size=args.batch_size, validation=validation, validate_every=args.validate_every,
        out=out, checkpoint_every=args.checkpoint_every, resume=args.resume,
        history_format=args.history, dtype=jnp.float32, progress=args.progress,
    )
    last = result.history[-1] if result.history else {}
    print(json.dumps({
        "out": str(out), "model": args.model, "steps": result.step, "seconds": round(result.seconds, 2),
        "loss": last.get("loss"), "validation": last.get("validation"),
    }))
    return 0


def register(subparsers) -> None:
    """Add `cldyn fit` to the command line."""
    parser = subparsers.add_parser(
        "fit",
        help="learn a KeyCLD model or a baseline from keypoint trajectories",
        description=(
            "Fit a KeyCLD model (point masses, MLP potential and input matrix, the scene's constraints), "
            "KeyCLD-NC (no constraint) or NODE2 (second-order neural ODE) to keypoint trajectories: a "
            "KeyCLD scene recorded with MuJoCo in the paper's protocol (--scene) or a file (--data: "
            "cldyn.Sequences.save or cldyn.mujoco.Recording.save). Writes fit.json, model.eqx, "
            "checkpoint.eqx and history.json to --out; prints a JSON summary."
        ),
    )
    source = parser.add_argument_group("data")
    source.add_argument("--data", help="a .npz written by Sequences.save or Recording.save")
    source.add_argument("--scene", choices=("pendulum", "cartpole", "acrobot"), help="a KeyCLD scene")
    source.add_argument("--runs", type=int, default=500, help="runs to record for --scene (500)")
    source.add_argument("--frames", type=int, default=50, help="frames per run for --scene (50)")
    source.add_argument("--noise", type=float, default=0.0, help="keypoint noise (m) for --scene")
    source.add_argument("--data-seed", type=int, default=0, help="seed of the recorded data (0)")
    source.add_argument("--origin", type=float, nargs=2, metavar=("X", "Y"),
                        help="point subtracted from the keypoints (default: the pivot of a KeyCLD scene)")
    source.add_argument("--validation-runs", type=int, default=50,
                        help="the last N runs validate (50, as in the paper; 0 for none)")
    model = parser.add_argument_group("model")
    model.add_argument("--model", choices=MODELS, default="keycld", help="the model (keycld)")
    model.add_argument("--constraint", choices=("pendulum", "cartpole", "acrobot"),
                       help="KeyCLD's constraints for this system (default: from the scene)")
    model.add_argument("--width", type=int, help="hidden width (32; NODE2: 64)")
    model.add_argument("--depth", type=int, help="hidden layers (2; NODE2: 3)")
    training = parser.add_argument_group("training")
    training.add_argument("--out", required=True, help="output directory")
    training.add_argument("--loss", choices=LOSSES, default="collocation", help="the loss (collocation)")
    training.add_argument("--steps", type=int, default=5000, help="optimiser steps (5000)")
    training.add_argument("--batch-size", type=int, default=32, help="runs per step (32)")
    training.add_argument("--lr", type=float, default=3e-3, help="peak learning rate (3e-3)")
    training.add_argument("--clip", type=float, default=5.0, help="element-wise gradient clipping (5)")
    training.add_argument("--seed", type=int, default=0, help="seed of the model and the batches (0)")
    training.add_argument("--resume", action="store_true", help="continue from --out/checkpoint.eqx")
    training.add_argument("--validate-every", type=int, default=250, help="steps between validations")
    training.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    training.add_argument("--history", choices=("json", "csv"), default="json", help="history format")
    training.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    parser.set_defaults(run=_fit)
