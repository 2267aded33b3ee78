"""`fit`: the one training loop, for models of keypoint states and (through keyvision) of images.

Steps run in chunks between two log, validation or checkpoint points (`cldyn._steps`: one compiled
`lax.while_loop`, or compiled steps dispatched asynchronously), so the host synchronises with the
device once per chunk, not once per step. The batch is sharded
over all local devices (`jax.sharding`, parameters replicated). Checkpoints (`cldyn._checkpoint`)
make an interrupted fit resumable with bitwise-equal results.
"""

import csv
import dataclasses
import hashlib
import io
import json
import os
import pathlib
import re
import time
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PRNGKeyArray, PyTree

from ._batching import AbstractBatching, Runs, num_runs
from ._checkpoint import CheckpointError, load_checkpoint, save_checkpoint, serialise
from ._custom_types import Scalar
from ._misc import atomic_write, check_positive
from ._progress import AbstractProgressMeter, NoProgressMeter
from ._steps import AbstractStepLoop, CompiledLoop, optax_promotion

_HISTORY_SCHEMA = "cldyn.FitHistory/1"
# Settings that must agree for a checkpoint to be resumed: together they fix every batch and update.
_RESUMED_SETTINGS = ("stage", "key", "loss", "batching", "dtype", "trainable", "data", "validation")
_STAGE = re.compile(r"[A-Za-z0-9_.-]+")


class NonFiniteLossError(RuntimeError):
    """`fit` met a NaN or infinite loss or gradient and stopped.

    **Attributes:** `step` (the step that failed, counted from 1), `model` (the last good model),
    `checkpoint` (the path of the last good checkpoint, or `None`), `before_any_update` (whether the
    call had applied no update yet: the model it started from fails, whatever the learning rate).
    """

    def __init__(
        self,
        message: str,
        *,
        step: int,
        model: Any,
        checkpoint: pathlib.Path | None,
        before_any_update: bool = False,
    ):
        super().__init__(message)
        self.step = step
        self.model = model
        self.checkpoint = checkpoint
        self.before_any_update = before_any_update


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What `fit` returns.

    **Fields:**

    - `model`: the trained model.
    - `history`: one dict per logged step: `step`, `loss` (mean training loss since the previous
      record), `validation` (when computed), `seconds` (training time so far), and what the
      callback added.
    - `step`: the number of optimiser steps taken in total.
    - `seconds`: training time in seconds, over all sessions of a resumed fit.
    - `out`: the output directory, or `None`.
    - `settings`: the fit's settings as recorded in the checkpoint and the history (stage, key,
      loss, batching, dtype, trainable parameters, data fingerprints, intervals, devices, the step
      loop's class: a resumed fit may run another loop or on other devices).
    """

    model: Any
    history: list[dict]
    step: int
    seconds: float
    out: pathlib.Path | None
    settings: dict


def fit_files(out: "str | os.PathLike", stage: str | None = None, history_format: str = "json") -> dict:
    """The files of a fit (`stage`) in directory `out`: `checkpoint`, `model` and `history` paths."""
    out, suffix = pathlib.Path(out), "" if stage is None else f"-{stage}"
    return {
        "checkpoint": out / f"checkpoint{suffix}.eqx",
        "model": out / f"model{suffix}.eqx",
        "history": out / f"history{suffix}.{history_format}",
    }


# -- helpers ---------------------------------------------------------------------------------------


def _trainable_spec(model, trainable):
    if trainable is None:
        return eqx.is_inexact_array
    if callable(trainable) and not isinstance(trainable, eqx.Module):
        spec = trainable(model)
        # a per-leaf filter such as `eqx.is_inexact_array` answers for the whole model with one bool
        return trainable if isinstance(spec, bool) else spec
    return trainable


def _partition(model, trainable):
    params, static = eqx.partition(model, _trainable_spec(model, trainable))
    params, frozen = eqx.partition(params, eqx.is_inexact_array)
    return params, eqx.combine(static, frozen)


def _cast(tree, dtype):
    if dtype is None:
        return tree
    return jax.tree.map(lambda a: a.astype(dtype) if eqx.is_inexact_array(a) else a, tree)


def _key_data(key) -> list[int]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return [int(v) for v in np.asarray(key).reshape(-1)]


def _describe(thing) -> str | None:
    """A description that is the same in every process for the same setting (no addresses)."""
    if thing is None:
        return None
    if isinstance(thing, eqx.Module):
        return eqx.tree_pformat(thing)  # arrays as dtype[shape]: a large loss weight stays short
    name = getattr(thing, "__qualname__", None)
    if name is not None:
        return f"{getattr(thing, '__module__', '')}.{name}"
    return type(thing).__qualname__


def _fingerprint(tree) -> dict | None:
    """Shapes, dtypes and a SHA-256 of the arrays and the structure (static fields included)."""
    if tree is None:
        return None
    arrays, rest = eqx.partition(tree, eqx.is_array)
    digest = hashlib.sha256(str(jax.tree.structure(rest)).encode())
    shapes = []
    for leaf in jax.tree.leaves(arrays):
        array = np.ascontiguousarray(np.asarray(leaf))
        shapes.append([list(array.shape), array.dtype.str])
        digest.update(repr(shapes[-1]).encode())
        digest.update(array.tobytes())
    return {"arrays": shapes, "sha256": digest.hexdigest()}


def _json_value(value):
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


def _write_history(path: pathlib.Path, settings: dict, history: list[dict]) -> None:
    if path.suffix == ".json":
        text = json.dumps({"schema": _HISTORY_SCHEMA, "settings": settings, "records": history}, indent=1)
        atomic_write(path, text)
        return
    buffer = io.StringIO()
    buffer.write(f"# {json.dumps({'schema': _HISTORY_SCHEMA, 'settings': settings})}\n")
    fields = ["step", "loss", "validation", "seconds"]
    fields += sorted({name for row in history for name in row} - set(fields))
    writer = csv.DictWriter(buffer, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    for row in history:
        writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in fields})
    atomic_write(path, buffer.getvalue())


def _next(step: int, every: int) -> int:
    return (step // every + 1) * every


def _put(tree, sharding):
    arrays, rest = eqx.partition(tree, eqx.is_array)
    return eqx.combine(jax.device_put(arrays, sharding), rest)


# one object, not a fresh one per call: the compiled steps take the optimiser as a static argument,
# and an equal but new optimiser would compile them again for every `fit` of the same model
_DEFAULT_OPTIMIZER = optax.chain(optax.clip(5.0), optax.adam(3e-4))


@eqx.filter_jit
def _evaluate_loss(model, data, *, loss):
    return loss(model, data)


# -- fit -------------------------------------------------------------------------------------------


def fit(
    model: PyTree,
    data: PyTree,
    *,
    loss: Callable[[Any, Any], Scalar],
    steps: int,
    key: PRNGKeyArray,
    optimizer: optax.GradientTransformation | None = None,
    batching: AbstractBatching = Runs(32),
    validation: PyTree | None = None,
    validate_every: int = 100,
    log_every: int = 10,
    out: "str | os.PathLike | None" = None,
    checkpoint_every: int = 500,
    resume: bool = False,
    force: bool = False,
    stage: str | None = None,
    history_format: str = "json",
    trainable: Any = None,
    dtype: Any = jnp.float32,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
    callback: Callable[[int, Any], dict | None] | None = None,
    devices: Sequence[jax.Device] | None = None,
    loop: AbstractStepLoop = CompiledLoop(),
) -> FitResult:
    """Fit the parameters of a model to data by stochastic gradient descent.

    Every step draws a batch (`batching`, with the key `jax.random.fold_in(key, step)`, so a resumed
    fit draws the same batches), evaluates `loss(model, batch)` and applies one optimiser update to
    the trainable parameters. Steps run in chunks between log, validation and checkpoint points
    (`loop`): the host waits for the device once per chunk. The batch is sharded over `devices` (a 1-D
    mesh, parameters and data replicated); on one device nothing is sharded.

    **Arguments:**

    - `model`: the model, e.g. `cldyn.keycld_model(...)`, `cldyn.SecondOrderNeuralODE(...)`, or
      any Equinox module the loss takes.
    - `data`: the training data: a `Sequences`, or any PyTree whose arrays lead with the run axis
      (with `(runs, T)` for `Windows`).
    - `loss`: `loss(model, batch) -> scalar`, e.g. `cldyn.Collocation()` (eq. 11-13).
    - `steps`: the total number of optimiser steps (a resumed fit continues up to it).
    - `key`: a `jax.random` key for the batches.
    - `optimizer`: an optax optimiser; by default Adam with learning rate `3e-4` after element-wise
      gradient clipping at 5, as in the KeyCLD authors' code. The compiled step is kept for the next
      `fit` of a model of the same structure with the same loss, batching and optimiser object: pass
      one optimiser to several fits rather than building an equal one for each, which compiles anew.
    - `batching`: how batches are drawn: `cldyn.Runs(batch_size)` (whole runs, the default with 32)
      or `cldyn.Windows(batch_size, length)` (windows of consecutive samples).
    - `validation`: held-out data; their loss is computed every `validate_every` steps and at the end.
    - `log_every`: steps between history records (each the mean training loss since the last).
    - `out`: a directory for `history.json` (or `.csv`), `checkpoint.eqx` and the final `model.eqx`
      (with a `stage`, `checkpoint-<stage>.eqx` and so on); nothing is written without it.
    - `checkpoint_every`: steps between checkpoints (and one at the end). A checkpoint holds the
      model, the optimiser state, the step, the settings and the history in one hashed file written
      atomically, so an interrupted write never damages the last one.
    - `resume`: continue from the stage's checkpoint in `out` if there is one (otherwise start
      afresh). The result is bitwise that of an uninterrupted fit. A checkpoint written with another
      key, stage, loss, batching, dtype, set of trainable parameters or other data is refused with
      a `CheckpointError` that names the difference; `steps` may grow.
    - `force`: with `resume`, continue from a checkpoint even though it was written by another
      training (other data, loss, key, batching or validation data); its model and optimiser state
      must still have this fit's structure. The checkpoints written from then on record this fit's
      settings.
    - `stage`: a name for one stage of a staged schedule (letters, digits, `_.-`); its files carry
      the name, so stages in one directory neither overwrite nor resume each other.
    - `history_format`: `"json"` or `"csv"`.
    - `trainable`: which parameters to train: `None` (every inexact array), a filter-spec PyTree of
      booleans (a prefix of the model, as for `eqx.partition`), a function `model -> spec`, or a
      per-leaf filter function. Other leaves are frozen.
    - `dtype`: floating dtype of the parameters and data during training; `float32` by default.
      `None` keeps the dtypes given; float64 needs JAX's 64-bit mode.
    - `progress_meter`: how to show progress: `cldyn.NoProgressMeter()` (default),
      `cldyn.TextProgressMeter()` or `cldyn.TqdmProgressMeter()`; updated at every history record.
    - `callback`: `callback(step, model)` at every history record; a returned dict of numbers is
      added to the record (e.g. a diagnostic measured on the current model).
    - `devices`: the devices to shard the batch over; all local devices by default. The batch size
      must be a multiple of their number.
    - `loop`: how the steps between two log, validation or checkpoint points run:
      `cldyn.CompiledLoop()` (one compiled loop, the default) or `cldyn.HostLoop()` (one compiled
      step at a time; faster for convolutional networks on CPU).

    **Returns:** a `FitResult` with the trained model, the history and the settings.

    A non-finite loss or gradient at step `s` stops the fit with a `NonFiniteLossError` that names
    `s`; its update is not applied, the last checkpoint is left untouched, and the error carries the
    last good model. At the first step of a call no update has acted yet, and the error points at the
    data and the starting model rather than the learning rate. A checkpoint that cannot be read raises
    a `CheckpointError` naming the file.

    **Staged schedules** are successive calls on one directory, each with its `stage`, `trainable`
    and `loss`, each starting from the model the previous one returned. With `resume=True` on all
    of them a restarted script skips finished stages (their checkpoint is at their last step) and
    resumes the interrupted one.

    !!! example

        ```python
        model = cldyn.keycld_model(4, 2, cldyn.keycld_constraint("acrobot"), key=jax.random.key(0))
        result = cldyn.fit(model, train, loss=cldyn.Collocation(), steps=2000, batching=cldyn.Runs(32),
                           key=jax.random.key(1), validation=validation, out="runs/acrobot",
                           progress_meter=cldyn.TextProgressMeter())
        ```
    """
    steps = check_positive("fit: steps", steps, integer=True, allow_zero=True)
    log_every = check_positive("fit: log_every", log_every, integer=True)
    validate_every = check_positive("fit: validate_every", validate_every, integer=True)
    checkpoint_every = check_positive("fit: checkpoint_every", checkpoint_every, integer=True)
    if not callable(loss):
        raise TypeError(f"fit: loss must be a function loss(model, batch), got {type(loss).__name__}")
    if not isinstance(batching, AbstractBatching):
        raise TypeError(f"fit: batching must be cldyn.Runs(...) or cldyn.Windows(...), got {batching!r}")
    if not isinstance(progress_meter, AbstractProgressMeter):
        raise TypeError(f"fit: progress_meter must be an AbstractProgressMeter, got {progress_meter!r}")
    if history_format not in ("json", "csv"):
        raise ValueError(f"fit: history_format must be 'json' or 'csv', got {history_format!r}")
    if stage is not None and not (isinstance(stage, str) and _STAGE.fullmatch(stage)):
        raise ValueError(f"fit: stage must be a name of letters, digits and _.-, got {stage!r}")
    if dtype is not None and jnp.zeros((), dtype).dtype != jnp.dtype(dtype):
        raise ValueError(f"fit: dtype {jnp.dtype(dtype).name} needs JAX's 64-bit mode")
    if resume and out is None:
        raise ValueError("fit: resume=True needs the output directory `out`")
    if optimizer is not None and not isinstance(optimizer, optax.GradientTransformation):
        raise TypeError(
            f"fit: optimizer must be an optax.GradientTransformation, got {type(optimizer).__name__}"
        )
    if callback is not None and not callable(callback):
        raise TypeError("fit: callback must be a function callback(step, model)")
    batching.check(data)
    if validation is not None:
        num_runs(validation)
    devices = tuple(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ValueError("fit: no devices to train on")
    if batching.batch_size % len(devices):
        raise ValueError(
            f"fit: the batch of {batching.batch_size} does not split over {len(devices)} devices; "
            f"use a batch size that is a multiple of {len(devices)}"
        )
    files = None
    if out is not None:
        out = pathlib.Path(out)
        if out.exists() and not out.is_dir():
            raise NotADirectoryError(f"fit: the output {out} exists and is not a directory")
        out.mkdir(parents=True, exist_ok=True)
        files = fit_files(out, stage, history_format)
    optimizer = _DEFAULT_OPTIMIZER if optimizer is None else optimizer

    model, data, validation = _cast(model, dtype), _cast(data, dtype), _cast(validation, dtype)
    params, static = _partition(model, trainable)
    with optax_promotion():
        opt_state = optimizer.init(params)
    settings = {
        "stage": stage,
        "key": _key_data(key),
        "loss": _describe(loss),
        "batching": _describe(batching),
        "dtype": None if dtype is None else jnp.dtype(dtype).name,
        "trainable": [[list(a.shape), a.dtype.name] for a in jax.tree.leaves(params)],
        "data": _fingerprint(data),
        "validation": _fingerprint(validation),
        "steps": steps,
        "log_every": log_every,
        "validate_every": validate_every,
        "checkpoint_every": checkpoint_every,
        "devices": len(devices),
        "loop": type(loop).__name__,
    }
    settings = json.loads(json.dumps(settings))

    start, history, elapsed, saved_step = 0, [], 0.0, None
    if resume and files["checkpoint"].exists():
        checkpoint = files["checkpoint"]

        def same_training(header):
            recorded = header.get("settings")
            recorded = recorded if isinstance(recorded, dict) else {}
            changed = [name for name in _RESUMED_SETTINGS if recorded.get(name) != settings[name]]
            if changed and not force:
                raise CheckpointError(
                    f"checkpoint {checkpoint} was written by another training: its {', '.join(changed)} "
                    f"{'differs' if len(changed) == 1 else 'differ'} from this fit's; resume with the same "
                    "settings, pass force=True to continue anyway, or start afresh in another directory"
                )
            if not all(name in header for name in ("step", "history", "seconds")):
                raise CheckpointError(f"checkpoint {checkpoint} is corrupt: its header lacks the fit's state")

        (model, opt_state), header = load_checkpoint(checkpoint, (model, opt_state), check=same_training)
        params, static = _partition(model, trainable)
        start, history, elapsed = int(header["step"]), list(header["history"]), float(header["seconds"])
        saved_step = start

    if len(devices) > 1:
        mesh = Mesh(np.asarray(devices), ("batch",))
        replicated, sharding = (
            NamedSharding(mesh, PartitionSpec()),
            NamedSharding(mesh, PartitionSpec("batch")),
        )
    else:
        replicated, sharding = jax.sharding.SingleDeviceSharding(devices[0]), None
    params, opt_state, static = (
        _put(params, replicated),
        _put(opt_state, replicated),
        _put(static, replicated),
    )
    data, validation = _put(data, replicated), _put(validation, replicated)
    length = min(log_every, validate_every, checkpoint_every)

    def save(step, params, opt_state, seconds):
        nonlocal saved_step
        if files is None:
            return
        header = {"step": step, "seconds": seconds, "settings": settings, "history": history}
        save_checkpoint(files["checkpoint"], (eqx.combine(params, static), opt_state), header)
        _write_history(files["history"], settings, history)
        saved_step = step

    losses: list[float] = []
    clock = time.perf_counter()
    step = start
    meter = progress_meter.start(steps, initial=start, desc=stage or "fit", unit="step")
    try:
        while step < steps:
            stop = min(
                _next(step, log_every), _next(step, validate_every), _next(step, checkpoint_every), steps
            )
            new_params, new_opt_state, values, done, bad = loop.run(
                params,
                opt_state,
                static,
                data,
                key,
                step,
                stop - step,
                loss=loss,
                optimizer=optimizer,
                batching=batching,
                length=length,
                sharding=sharding,
            )
            done, bad, values = int(done), bool(bad), np.asarray(values)
            losses.extend(float(v) for v in values[:done])
            params, opt_state, step = new_params, new_opt_state, step + done
            if bad:
                where = (
                    "no checkpoint was written"
                    if saved_step is None
                    else (
                        f"the last good checkpoint is {files['checkpoint']} (step {saved_step}), "
                        "left untouched"
                    )
                )
                named = "" if stage is None else f" of stage {stage!r}"
                advice = (
                    # no update of this call came before: the learning rate played no part
                    "The model this fit started from already gives it, before any update, so a lower "
                    "learning rate cannot help: check the data for outliers and for states where the "
                    "model is singular (a keypoint on a constraint's pivot), and the starting model for "
                    "non-finite parameters."
                    if step == start
                    else "Lower the learning rate, check the data for outliers, or start from a checkpoint."
                )
                raise NonFiniteLossError(
                    f"fit: non-finite loss or gradient at step {step + 1}{named} (loss = {values[done]}); "
                    f"stopped without applying the update; {where}. {advice}",
                    step=step + 1,
                    model=eqx.combine(params, static),
                    checkpoint=None if saved_step is None else files["checkpoint"],
                    before_any_update=step == start,
                )
            last = step == steps
            if step % log_every == 0 or step % validate_every == 0 or last:
                record = {"step": step, "loss": _json_value(np.mean(losses)) if losses else None}
                losses = []
                if step % validate_every == 0 or last:
                    record["validation"] = (
                        None
                        if validation is None
                        else _json_value(_evaluate_loss(eqx.combine(params, static), validation, loss=loss))
                    )
                record["seconds"] = elapsed + time.perf_counter() - clock
                history.append(record)
                if callback is not None:
                    record.update(callback(step, eqx.combine(params, static)) or {})
                meter = progress_meter.update(
                    meter, step, {"loss": record["loss"], "validation": record.get("validation")}
                )
            if step % checkpoint_every == 0 or last:
                save(step, params, opt_state, elapsed + time.perf_counter() - clock)
    except KeyboardInterrupt:
        if saved_step != step:
            save(step, params, opt_state, elapsed + time.perf_counter() - clock)
        raise
    finally:
        progress_meter.close(meter)
    seconds = elapsed + time.perf_counter() - clock
    model = eqx.combine(params, static)
    if files is not None:
        if saved_step != step:
            save(step, params, opt_state, seconds)
        atomic_write(files["model"], serialise(model))
        _write_history(files["history"], settings, history)
    return FitResult(model=model, history=history, step=step, seconds=seconds, out=out, settings=settings)


# -- fit directories -------------------------------------------------------------------------------

SPEC_NAME = "fit.json"


def load_fit(directory: "str | os.PathLike") -> tuple[Any, dict]:
    """The trained model of a fit directory (written by `cldyn fit`), in the dtype it was trained in.

    The directory holds `fit.json` (the model's specification under `model`, the `seed` and the
    training `dtype`) and `model.eqx` (the trained parameters).

    **Arguments:**

    - `directory`: the directory.

    **Returns:** `(model, spec)` with the model and the parsed `fit.json`. A missing directory or
    file raises `FileNotFoundError`; a corrupt file or a model that does not match its
    specification raises a `ValueError` naming the file.

    !!! example

        ```python
        model, spec = cldyn.load_fit("runs/acrobot")
        ```
    """
    directory = pathlib.Path(directory)
    path = directory / SPEC_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{directory}: not a cldyn fit directory (no {SPEC_NAME})")
    try:
        spec = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: unreadable ({error})") from error
    if not isinstance(spec, dict) or "model" not in spec:
        raise ValueError(f"{path}: no model specification (the 'model' entry)")
    dtype = spec.get("dtype")
    from ._keycld import model_from_spec

    try:
        like = _cast(model_from_spec(spec["model"], key=jax.random.key(0)), dtype)
    except (ValueError, TypeError) as error:
        raise ValueError(f"{path}: {error}") from error
    model_path = fit_files(directory)["model"]
    if not model_path.is_file():
        raise FileNotFoundError(f"{model_path}: no such file (the fit did not finish?)")
    try:
        model = eqx.tree_deserialise_leaves(model_path, like)
    except Exception as error:  # a truncated or mismatched file; equinox raises several types
        raise ValueError(
            f"{model_path}: cannot load the trained model ({type(error).__name__}: {error})"
        ) from error
    return model, spec
