"""A trained KeyCLD model on disk: `keyvision.json` (every size, the dynamics' cldyn spec, the data,
the seed and the schedule) and `model.eqx` (the parameters), as `keyvision train` writes them."""

import json
import os
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

import cldyn
from cldyn._misc import atomic_save, atomic_write

from ._estimator import KeypointEstimator, KeypointEstimatorFC
from ._model import KeyCLD
from ._renderer import Renderer, RendererFC

SPEC_NAME = "keyvision.json"
MODEL_NAME = "model.eqx"
_SIZES = ("keypoints", "width", "image_size", "dynamics")
INITIAL_NAME = "model-initial.eqx"  # the starting networks of a training that took them from another
# the estimator and renderer of each kind of networks: the paper's U-Nets, or its FC ablation (A.4)
NETWORKS = {"unet": (KeypointEstimator, Renderer), "fc": (KeypointEstimatorFC, RendererFC)}


def trained_supersample(spec: dict) -> int:
    """The samples per pixel side of the camera whose frames a model was trained on (its
    `keyvision.json`'s `data.supersample`; 1, MuJoCo's render, for models written before it)."""
    return int((spec.get("data") or {}).get("supersample", 1))


def model_from_spec(spec: dict, *, key: PRNGKeyArray) -> KeyCLD:
    """The untrained float32 `KeyCLD` that a specification describes.

    The paper's estimator and renderer (U-Nets of `spec["width"]` channels for frames of
    `spec["image_size"]` pixels, `spec["keypoints"]` keypoints; with `spec["networks"] == "fc"` the
    FC ablation, `KeypointEstimatorFC` and `RendererFC`) around the cldyn dynamics of
    `spec["dynamics"]` (`cldyn.model_from_spec`). Float32 even where JAX's 64-bit mode is on: the
    networks' and the images' precision.

    **Arguments:**

    - `spec`: a dict with the entries `keypoints`, `width`, `image_size` and `dynamics`, and
      optionally `networks` (`"unet"`, the default, or `"fc"`): what `keyvision train` writes to
      `keyvision.json`; other entries are ignored.
    - `key`: the initialisation key.

    **Returns:** the `KeyCLD`. A missing entry raises a `KeyError` naming it.

    !!! example

        ```python
        spec = {"keypoints": 1, "width": 16, "image_size": 64,
                "dynamics": {"kind": "keycld", "size": 2, "num_inputs": 1, "constraint": "pendulum",
                             "width": 32, "depth": 2}}
        model = keyvision.model_from_spec(spec, key=jax.random.key(0))
        ```
    """
    missing = [name for name in _SIZES if name not in spec]
    if missing:
        raise KeyError(f"the model specification lacks {', '.join(missing)}")
    networks = spec.get("networks", "unet")
    if networks not in NETWORKS:
        raise ValueError(
            f"the model specification's networks {networks!r}: choose one of {', '.join(NETWORKS)}"
        )
    estimator, renderer = NETWORKS[networks]
    keys = jax.random.split(key, 3)
    sizes = {"width": spec["width"], "image_size": spec["image_size"]}
    model = KeyCLD(
        estimator(spec["keypoints"], **sizes, key=keys[0]),
        cldyn.model_from_spec(spec["dynamics"], key=keys[1]),
        renderer(spec["keypoints"], **sizes, key=keys[2]),
    )
    return jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, model)


def save_model(directory: "str | os.PathLike", model: KeyCLD, spec: dict) -> pathlib.Path:
    """Write a model and its specification to `directory` (created if needed), each file atomically.

    **Arguments:**

    - `directory`: where `keyvision.json` and `model.eqx` go.
    - `model`: the trained `KeyCLD`, which must match `model_from_spec(spec)`.
    - `spec`: its specification (see `model_from_spec`); any further JSON entries are kept.

    **Returns:** the directory. `keyvision.load_model` reads it back.
    """
    like = eqx.filter_eval_shape(model_from_spec, spec, key=jax.random.key(0))  # shapes only, no work
    if jax.tree.structure(like) != jax.tree.structure(model) or any(
        np.shape(a) != np.shape(b) for a, b in zip(jax.tree.leaves(like), jax.tree.leaves(model))
    ):
        raise ValueError("save_model: the model does not match its specification")
    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    atomic_write(directory / SPEC_NAME, json.dumps(spec, indent=1))
    atomic_save(directory / MODEL_NAME, lambda temporary: eqx.tree_serialise_leaves(temporary, model))
    return directory


def _deserialise(path: pathlib.Path, like):
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        return eqx.tree_deserialise_leaves(path, like)
    except Exception as error:  # a truncated or mismatched file; equinox raises several types
        raise ValueError(f"{path}: cannot load the trained model ({type(error).__name__}: {error})") from None


def _load_stage(directory: pathlib.Path, spec: dict, like: KeyCLD, stage: str) -> KeyCLD:
    """The model as `keyvision.train` left it after `stage`, from the stages' `model-<stage>.eqx`."""
    from ._assign import ORDER_NAME, read_order, renumbered
    from ._train import stages_run

    stages = stages_run(spec.get("schedule") or {})
    if stage not in stages:
        raise ValueError(
            f"{directory}: no stage {stage!r} in this training (its stages: {', '.join(stages)})"
        )
    done = stages[: stages.index(stage) + 1]
    # the stages that train the networks (and the dynamics with them), saving the whole model
    networks = [s for s in done if s in ("autoencoder", "rigid") or s.startswith(("joint", "candidate-"))]
    if networks:
        model = _deserialise(directory / f"model-{networks[-1]}.eqx", like)
        after = done[done.index(networks[-1]) + 1 :]
    elif (directory / INITIAL_NAME).is_file():  # the networks this training started from
        model, after = _deserialise(directory / INITIAL_NAME, like), done
    else:  # the networks as initialised: `keyvision train` draws them from the first half of its seed
        model = model_from_spec(spec, key=jax.random.split(jax.random.key(spec.get("seed", 0)))[0])
        after = done
    # stage (b) renumbered the keypoints of stage (a), unless the rigid stage had (and saved them so)
    if "dynamics" in after and "rigid" not in done and model.num_keypoints > 1:
        order_path = directory / ORDER_NAME
        try:
            order = read_order(order_path)
        except FileNotFoundError:
            raise FileNotFoundError(
                f"{order_path}: no such file (trained before the keypoint order was recorded); stage "
                f"{stage!r} cannot be rebuilt"
            ) from None
        except ValueError as error:
            raise ValueError(f"{order_path}: unreadable keypoint order ({error})") from None
        if list(order) != list(range(model.num_keypoints)):
            model = renumbered(model, order)
    if after:
        dynamics = _deserialise(directory / f"model-{after[-1]}.eqx", model.dynamics)
        model = eqx.tree_at(lambda m: m.dynamics, model, dynamics)
    return model


def load_model(directory: "str | os.PathLike", *, stage: str | None = None) -> tuple[KeyCLD, dict]:
    """The trained model of a directory written by `keyvision train` (or `save_model`).

    **Arguments:**

    - `directory`: the directory with `keyvision.json` and `model.eqx`.
    - `stage`: `None` for the finished model (`model.eqx`), or the name of a stage of
      `keyvision.train` (`"autoencoder"`, `"dynamics"`, `"joint"`, `"refit"`, `"joint-2"`, ...) for
      the model as the training left it after that stage, rebuilt from the stages' files
      (`model-<stage>.eqx`, and `keypoint-order.json` for the dynamics stage): how far each stage
      took the model, also while later stages still train.

    **Returns:** `(model, spec)`. A missing directory or file raises `FileNotFoundError`; a corrupt
    file, parameters that do not match the specification or a stage that the training does not
    have raise a `ValueError` naming the file or the stage.

    !!! example

        ```python
        model, spec = keyvision.load_model("runs/pendulum")
        after_round_1, _ = keyvision.load_model("runs/pendulum", stage="refit")
        ```
    """
    directory = pathlib.Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: no such directory")
    spec_path, model_path = directory / SPEC_NAME, directory / MODEL_NAME
    for file in (spec_path,) if stage is not None else (spec_path, model_path):
        if not file.is_file():
            raise FileNotFoundError(f"{directory}: no {file.name} (not a finished keyvision train)")
    try:
        spec = json.loads(spec_path.read_text())
        like = eqx.filter_eval_shape(model_from_spec, spec, key=jax.random.key(0))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{spec_path}: unreadable model description ({error!r})") from None
    if stage is not None:
        return _load_stage(directory, spec, like, stage), spec
    return _deserialise(model_path, like), spec
