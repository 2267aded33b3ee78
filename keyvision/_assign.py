"""Numbering the keypoints of a trained autoencoder after the roles its constraints give them, and
judging by those constraints which of several autoencoders placed its keypoints best."""

import itertools
import json
import math
import pathlib
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

import cldyn
from cldyn._fit import fit_files
from cldyn._misc import atomic_write

from ._data import ImageSequences
from ._evaluate import encode_sequences
from ._model import KeyCLD

ORDER_NAME = "keypoint-order.json"  # the order of `assign_keypoints` after stage (a)
CHOICE_NAME = "candidates.json"  # the candidates' scores and the one chosen (`choose_candidate`)
_CHOICE_SCHEMA = "keyvision.Candidates/1"
_MAX_ASSIGNED = 6  # keypoints: every order is tried (720 at most)


@eqx.filter_jit
def _constraint_spread(constraint, x: Array) -> Array:
    """The mean over runs of the variance over time of each constraint value, `x` `(R, T, k)`."""
    values = jax.vmap(jax.vmap(constraint))(x)
    return jnp.mean(jnp.var(values, axis=1), axis=0)


def assign_keypoints(model: KeyCLD, keypoints: cldyn.Sequences) -> tuple[KeyCLD, tuple[int, ...]]:
    """Number the keypoints of a trained autoencoder so that they keep the dynamics' constraints.

    Stage (a) of `keyvision.train` places the keypoints by reconstruction alone, in no particular
    order, while the constraints of the dynamics give each keypoint a role (in KeyCLD's cart-pole
    keypoint 0 is the cart, whose height is fixed, and keypoint 1 the pole's end at a fixed
    distance from it). Of every order of the keypoints, the one whose constraint values vary least
    within the runs, $\\sum_j \\operatorname{mean}_r \\operatorname{Var}_t \\Phi_j(x_{r,t})$, is
    applied to the estimator's outputs and the renderer's inputs (`permute`): the autoencoder draws
    the same images, with its keypoints renumbered.

    **Arguments:**

    - `model`: a `keyvision.KeyCLD` whose dynamics have constraints (others are returned as given).
    - `keypoints`: the encoded training runs, `cldyn.Sequences` (`keyvision.encode_sequences`).

    **Returns:** `(model, order)`: the renumbered model and the order, keypoint `k` being the old
    keypoint `order[k]`.

    !!! example

        ```python
        model, order = keyvision.assign_keypoints(model, keyvision.encode_sequences(model, data))
        ```
    """
    count = model.num_keypoints
    identity = tuple(range(count))
    constraint = getattr(model.dynamics, "constraint", None)
    if constraint is None or count == 1:
        return model, identity
    if count > _MAX_ASSIGNED:
        warnings.warn(
            f"assign_keypoints: {count} keypoints have {math.factorial(count)} orders; left as they are",
            stacklevel=2,
        )
        return model, identity
    x = jnp.asarray(keypoints.x).reshape(*keypoints.x.shape[:2], count, 2)
    spreads = {
        order: float(jnp.sum(_constraint_spread(constraint, x[:, :, list(order)].reshape(keypoints.x.shape))))
        for order in itertools.permutations(identity)
    }
    order = min(spreads, key=spreads.get)
    if order == identity:
        return model, identity
    return renumbered(model, order), order


def renumbered(model: KeyCLD, order) -> KeyCLD:
    """`model` with keypoint `k` being its keypoint `order[k]`: the order applied to the estimator's
    outputs and the renderer's inputs (`permute`), the dynamics as they are."""
    return KeyCLD(model.estimator.permute(order), model.dynamics, model.renderer.permute(order))


def assign_and_record(model: KeyCLD, keypoints: cldyn.Sequences, out: pathlib.Path | None):
    """`assign_keypoints`, and the order recorded in `out` (what `keyvision.load_model` needs to
    rebuild the stages after stage (a))."""
    model, order = assign_keypoints(model, keypoints)
    if out is not None:
        atomic_write(out / ORDER_NAME, json.dumps({"keypoint_order": list(order)}))
    return model, order


def read_order(path: pathlib.Path) -> tuple:
    """The keypoint order that `assign_and_record` recorded in `path`: a `FileNotFoundError` if there is none,
    a `ValueError` (holding the reason) if it cannot be read."""
    try:
        return tuple(json.loads(path.read_text())["keypoint_order"])
    except FileNotFoundError:
        raise
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as error:
        raise ValueError(repr(error)) from None


def rigid_order(model: KeyCLD, data: ImageSequences, out: pathlib.Path | None, resume: bool):
    """The rigid stage's numbering: on resume, once that stage has checkpointed, the order it
    recorded (the networks it fitted were numbered so; encoding every training frame again would
    only repeat it, and on a GPU need not reproduce it bitwise); otherwise `assign_and_record` afresh."""
    path = None if out is None else out / ORDER_NAME
    if not (resume and path is not None and fit_files(out, "rigid")["checkpoint"].exists()):
        return assign_and_record(model, encode_sequences(model, data), out)
    try:
        order = read_order(path)
        valid = sorted(order) == list(range(model.num_keypoints))
    except (OSError, ValueError, TypeError) as error:  # absent, unreadable, or entries that do not sort
        order, valid = error, False
    if not valid:
        raise cldyn.CheckpointError(
            f"{path}: not the keypoint order of {model.num_keypoints} keypoints that the checkpoint of "
            f"stage 'rigid' was numbered by (read: {order}); delete it and checkpoint-rigid.eqx to run "
            "that stage afresh"
        )
    if order != tuple(range(model.num_keypoints)):
        model = renumbered(model, order)
    return model, order


def _motion_spread(constraint, x: Array) -> Array:
    """`constraint_score`'s value on frames `x` `(frames, 2K)`, keypoints in the constraints' order."""
    frames, size = x.shape
    values = jax.vmap(constraint)(x)
    jacobian = jax.vmap(constraint.jacobian)(x).reshape(frames, -1, size // 2, 2)
    sensitivity = jnp.mean(jnp.sum(jacobian**2, axis=-1), axis=0)  # (constraints, keypoints)
    motion = jnp.sum(jnp.var(x.reshape(frames, size // 2, 2), axis=0), axis=-1)  # (keypoints,)
    chance = sensitivity @ motion / 2
    tiny = jnp.finfo(x.dtype).tiny
    # keypoints that do not move at all tell nothing: as bad as keypoints unrelated to the bodies
    ratio = jnp.where(chance > tiny, jnp.var(values, axis=0) / jnp.maximum(chance, tiny), 1.0)
    return jnp.mean(ratio)


def constraint_score(model: KeyCLD, keypoints: cldyn.Sequences) -> float:
    """How far the keypoints of an autoencoder are from keeping the constraints of its dynamics.

    Reconstruction places the keypoints wherever the renderer can draw the frames from, and two
    initialisations of the same networks may place them very differently: of three cart-pole
    autoencoders trained alike, one put both its keypoints on one point of the pole, 3.7 pixels
    apart where the cart and the pole's end are 12.8 pixels apart, and the dynamics learnt on them
    predicted for a third as long as those of the best (`docs/ablation.md`). The constraints tell
    such autoencoders apart without any ground truth. With the keypoints numbered as
    `keyvision.assign_keypoints` numbers them, $\\Phi_c$ the constraints of `model.dynamics` and
    $x_k$ keypoint $k$ over every frame of every run,

    $$s = \\operatorname{mean}_c \\frac{\\operatorname{Var} \\Phi_c(x)}
    {\\tfrac12 \\sum_k \\operatorname{mean} \\lVert \\partial \\Phi_c / \\partial x_k \\rVert^2
    \\operatorname{tr} \\operatorname{Cov} x_k}:$$

    each constraint's variance over the variance it would have if the keypoints moved as much as
    they do, in directions unrelated to it. It is 0 for keypoints on rigid points of the bodies,
    about 1 for a keypoint that jitters about one place, and of that order for keypoints that
    wander (0.24 for one drawn uniformly over a square about a pendulum's pivot), whatever the
    lengths and the picture's scale. So neither drawing keypoints together nor holding them still
    lowers it. Set against a distance's mean square instead (this score's first form), a pendulum
    keypoint that hardly moves keeps its distance from the pivot as well as one on the bob, and
    scores as well.

    **Arguments:**

    - `model`: a `keyvision.KeyCLD` whose dynamics have constraints.
    - `keypoints`: its keypoints of the training runs, `cldyn.Sequences` (`keyvision.encode_sequences`).

    **Returns:** the score `s`, a float; lower is better.

    !!! example

        ```python
        score = keyvision.constraint_score(model, keyvision.encode_sequences(model, data))
        ```
    """
    constraint = getattr(model.dynamics, "constraint", None)
    if constraint is None:
        raise ValueError(
            f"constraint_score: needs dynamics with constraints, got {type(model.dynamics).__name__} "
            "without any"
        )
    shape = keypoints.x.shape
    if shape[-1] != 2 * model.num_keypoints:
        raise ValueError(
            f"constraint_score: keypoints of {shape[-1]} coordinates for a model of "
            f"{model.num_keypoints} keypoints"
        )
    _, order = assign_keypoints(model, keypoints)
    x = jnp.asarray(keypoints.x).reshape(*shape[:2], -1, 2)[:, :, list(order)].reshape(-1, shape[-1])
    return float(_motion_spread(constraint, x))


def choose_candidate(
    trials: dict[str, cldyn.FitResult],
    data: ImageSequences,
    out: pathlib.Path | None,
    resume: bool,
    progress_meter: cldyn.AbstractProgressMeter = cldyn.NoProgressMeter(),
    *,
    runs: int | None = None,
) -> dict:
    """Of the candidates' trials (their fits by stage name), the one that `keyvision.train` continues:
    the lowest `constraint_score` on the training frames (a non-finite score counts as the worst).

    The choice and every score are recorded in `out/candidates.json`; on resume the recorded choice
    is kept (a GPU need not encode the frames bitwise alike twice), unless the record is unreadable
    and stage (a) has not checkpointed yet, when the candidates are scored again. Scoring encodes
    every frame of the runs scored once per candidate: at most `runs` of them (`Schedule.candidate_runs`),
    every `k`-th run with `k = ceil(data.num_runs / runs)`; all by default. `progress_meter` counts
    the candidates scored.

    **Returns:** the record: `{"stages": [...], "scores": [...], "chosen": stage, "runs": scored}`.
    """
    names = list(trials)
    path = None if out is None else out / CHOICE_NAME
    if resume and path is not None and path.exists():
        try:
            record = json.loads(path.read_text())
            valid = record.get("schema") == _CHOICE_SCHEMA and record.get("stages") == names
            valid = valid and record.get("chosen") in names
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError) as error:
            record, valid = repr(error), False
        if valid:
            return record
        if fit_files(out, "autoencoder")["checkpoint"].exists():
            raise cldyn.CheckpointError(
                f"{path}: not a choice among the candidates {names} (read: {record}); stage (a) was "
                f"started from one of them: delete {path.name} and checkpoint-autoencoder.eqx to choose "
                "afresh"
            )
    every = 1 if runs is None else -(-data.num_runs // runs)
    scored = jax.tree.map(lambda a: a[::every], data) if every > 1 else data
    scores = {}
    meter = progress_meter.start(len(names), desc="scoring candidates", unit="candidate")
    try:
        for name, fitted in trials.items():
            scores[name] = constraint_score(fitted.model, encode_sequences(fitted.model, scored))
            meter = progress_meter.update(meter, len(scores), {"score": scores[name]})
    finally:
        progress_meter.close(meter)
    chosen = min(names, key=lambda name: scores[name] if math.isfinite(scores[name]) else math.inf)
    record = {
        "schema": _CHOICE_SCHEMA,
        "stages": names,
        "scores": [scores[name] if math.isfinite(scores[name]) else None for name in names],
        "chosen": chosen,
        "runs": scored.num_runs,
    }
    if path is not None:
        atomic_write(path, json.dumps(record, indent=1))
    return record
