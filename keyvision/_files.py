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

from ._estimator import KeypointEstimator
from ._model import KeyCLD
from ._renderer import Renderer

SPEC_NAME = "keyvision.json"
MODEL_NAME = "model.eqx"
_SIZES = ("keypoints", "width", "image_size", "dynamics")


def model_from_spec(spec: dict, *, key: PRNGKeyArray) -> KeyCLD:
    """The untrained float32 `KeyCLD` that a specification describes.

    The paper's estimator and renderer (U-Nets of `spec["width"]` channels for frames of
    `spec["image_size"]` pixels, `spec["keypoints"]` keypoints) around the cldyn dynamics of
    `spec["dynamics"]` (`cldyn.model_from_spec`). Float32 even where JAX's 64-bit mode is on: the
    networks' and the images' precision.

    **Arguments:**

    - `spec`: a dict with the entries `keypoints`, `width`, `image_size` and `dynamics` (what
      `keyvision train` writes to `keyvision.json`; other entries are ignored).
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
    keys = jax.random.split(key, 3)
    sizes = {"width": spec["width"], "image_size": spec["image_size"]}
    model = KeyCLD(
        KeypointEstimator(spec["keypoints"], **sizes, key=keys[0]),
        cldyn.model_from_spec(spec["dynamics"], key=keys[1]),
        Renderer(spec["keypoints"], **sizes, key=keys[2]),
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


def load_model(directory: "str | os.PathLike") -> tuple[KeyCLD, dict]:
    """The trained model of a directory written by `keyvision train` (or `save_model`).

    **Arguments:**

    - `directory`: the directory with `keyvision.json` and `model.eqx`.

    **Returns:** `(model, spec)`. A missing directory or file raises `FileNotFoundError`; a corrupt
    file or parameters that do not match the specification raise a `ValueError` naming the file.

    !!! example

        ```python
        model, spec = keyvision.load_model("runs/pendulum")
        ```
    """
    directory = pathlib.Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: no such directory")
    spec_path, model_path = directory / SPEC_NAME, directory / MODEL_NAME
    for file in (spec_path, model_path):
        if not file.is_file():
            raise FileNotFoundError(f"{directory}: no {file.name} (not a finished keyvision train)")
    try:
        spec = json.loads(spec_path.read_text())
        like = eqx.filter_eval_shape(model_from_spec, spec, key=jax.random.key(0))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{spec_path}: unreadable model description ({error!r})") from None
    try:
        model = eqx.tree_deserialise_leaves(model_path, like)
    except Exception as error:  # a truncated or mismatched file; equinox raises several types
        raise ValueError(
            f"{model_path}: cannot load the trained model ({type(error).__name__}: {error})"
        ) from None
    return model, spec
