"""What the keyvision commands share: where the frames and the trained model live in a directory,
and how a model directory is rebuilt (its `keyvision.json` names every size, `model.eqx` holds the
parameters)."""

import os
import pathlib

from cldyn._cli._common import CommandError, input_file

from .._files import MODEL_NAME, SPEC_NAME

FRAMES_NAME = "frames.npz"  # what `keyvision render` writes into --out


def frames_file(path: str, option: str) -> pathlib.Path:
    """The frames file `path`, or `path/frames.npz` for a directory written by `keyvision render`."""
    file = pathlib.Path(path)
    if file.is_dir():
        file = file / FRAMES_NAME
    return input_file(file, option)


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


def load_model(directory: str, option: str, stage: str | None = None):
    """`(model, spec)` of a directory written by `keyvision train` (`keyvision.load_model`), the
    finished model or, with `stage`, the model as the training left it after that stage."""
    import keyvision

    if stage is None:
        model_files(directory, option)
    elif not pathlib.Path(directory).is_dir():
        raise CommandError(f"{option} {directory}: no such directory")
    try:
        return keyvision.load_model(directory, stage=stage)
    except (FileNotFoundError, ValueError) as error:
        raise CommandError(str(error)) from None


def other_scene(frames, spec: dict) -> str:
    """What to add to an error about frames that do not fit a model: the two scenes, where they differ
    (" (frames of keycld/cartpole; the model was trained on keycld/pendulum)"), else nothing."""
    seen, trained_on = frames.info.get("scene"), (spec.get("data") or {}).get("scene")
    if not seen or not trained_on or seen == trained_on:
        return ""
    return f" (frames of {seen}; the model was trained on {trained_on})"


def model_and_frames(directory: str, data_path: pathlib.Path):
    """`(model, spec, frames)`: the model of `--model` and the frames of `--data`, checked to be of
    the model's size (the error names both scenes where they differ)."""
    import keyvision

    model, spec = load_model(directory, "--model")
    frames = keyvision.Frames.load(data_path)
    if frames.image_size != (model.image_size, model.image_size):
        raise CommandError(
            f"--data: frames of {frames.image_size} pixels; the model takes {model.image_size} x "
            f"{model.image_size}" + other_scene(frames, spec)
        )
    return model, spec, frames


def relative_path(path, out) -> str:
    """`path` as `keyvision.json` records it: relative to the model's directory `out`, so that the
    record holds wherever the two move together and names no machine's directories (absolute where no
    relative path exists, as across drives)."""
    try:
        return os.path.relpath(path, out)  # takes both relative to the working directory
    except ValueError:
        return os.path.abspath(path)
