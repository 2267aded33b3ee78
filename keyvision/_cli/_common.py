"""What the keyvision commands share: where the frames and the trained model live in a directory,
and how a model directory is rebuilt (its `keyvision.json` names every size, `model.eqx` holds the
parameters)."""

import json
import pathlib

from cldyn._cli._common import CommandError, input_file

FRAMES_NAME = "frames.npz"  # what `keyvision render` writes into --out
SPEC_NAME = "keyvision.json"  # the model's sizes, the dynamics' cldyn spec, the data and the schedule
MODEL_NAME = "model.eqx"  # the trained parameters


def frames_file(path: str, option: str) -> pathlib.Path:
    """The frames file `path`, or `path/frames.npz` for a directory written by `keyvision render`."""
    file = pathlib.Path(path)
    if file.is_dir():
        file = file / FRAMES_NAME
    return input_file(file, option)


def build_model(spec: dict, *, key):
    """The untrained float32 `KeyCLD` of a spec: the paper's estimator and renderer (U-Nets of
    `width`) and the cldyn dynamics of `spec["dynamics"]` (`cldyn.model_from_spec`)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import cldyn
    import keyvision

    keys = jax.random.split(key, 3)
    sizes = {"width": spec["width"], "image_size": spec["image_size"]}
    model = keyvision.KeyCLD(
        keyvision.KeypointEstimator(spec["keypoints"], **sizes, key=keys[0]),
        cldyn.model_from_spec(spec["dynamics"], key=keys[1]),
        keyvision.Renderer(spec["keypoints"], **sizes, key=keys[2]),
    )
    # float32 even where JAX's 64-bit mode is on (the networks' and the images' precision)
    return jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, model)


def model_files(directory: str, option: str) -> tuple[pathlib.Path, pathlib.Path]:
    """`(keyvision.json, model.eqx)` of a directory written by `keyvision train`, checked to exist."""
    directory = pathlib.Path(directory)
    if not directory.is_dir():
        raise CommandError(f"{option} {directory}: no such directory")
    spec, model = directory / SPEC_NAME, directory / MODEL_NAME
    for file in (spec, model):
        if not file.is_file():
            raise CommandError(f"{option} {directory}: no {file.name} (not a finished keyvision train)")
    return spec, model


def load_model(directory: str, option: str):
    """`(model, spec)` of a directory written by `keyvision train`."""
    import equinox as eqx
    import jax

    spec_path, model_path = model_files(directory, option)
    try:
        spec = json.loads(spec_path.read_text())
        like = build_model(spec, key=jax.random.key(0))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as error:
        raise CommandError(f"{spec_path}: unreadable model description ({error!r})") from None
    try:
        model = eqx.tree_deserialise_leaves(model_path, like)
    except Exception as error:  # a truncated or mismatched file; equinox raises several types
        raise CommandError(
            f"{model_path}: cannot load the trained model ({type(error).__name__}: {error})"
        ) from None
    return model, spec
