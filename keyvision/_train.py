"""Training KeyCLD from images in stages, each one call of `cldyn.fit` (no second training loop).

Joint training from scratch is slow on a CPU and reconstruction alone does not place the
keypoints, so the recipe has four stages: (a) the autoencoder (estimator and renderer) on single
frames, (b) the dynamics on the keypoints of the frozen estimator (cheap: no images involved),
(c) everything jointly on short windows of frames, which makes the keypoints consistent with the
dynamics and far less noisy, and (d) the dynamics alone again on those keypoints, by multiple
shooting.
"""

import dataclasses
import functools
import json
import os
import pathlib
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import PRNGKeyArray

import cldyn
from cldyn._data import _read_npz as read_npz
from cldyn._fit import fit_files
from cldyn._misc import atomic_save, atomic_write, check_positive

from ._assign import assign_and_record, choose_candidate, rigid_order
from ._augment import Augment
from ._data import ImageSequences
from ._evaluate import encode_sequences
from ._loss import ConstraintDrift, HeatmapRegulariser, KeypointDynamics, Reconstruction
from ._model import KeyCLD

_SCHEMA = "keyvision.Train/1"
_STAGES = ("autoencoder", "dynamics", "joint")
_KEYPOINTS_SCHEMA = "keyvision.StageKeypoints/1"


@dataclasses.dataclass(frozen=True)
class Schedule:
    """The staged training recipe of `keyvision.train`.

    **Fields:**

    - `autoencoder_steps`: steps of stage (a), estimator and renderer on single frames with
      `Reconstruction() + heatmap_weight * HeatmapRegulariser()`; the dynamics stay frozen.
    - `autoencoder_batch`: frames per step of stage (a), and of the rigid stage.
    - `candidates`, `candidate_steps`: with `candidates` above 1, `keyvision.train` takes that many
      initial models (the same networks drawn from different keys), gives each a trial of
      `candidate_steps` steps of stage (a) (stages `candidate-1`, `candidate-2`, ...), and stage (a)
      continues the one whose keypoints best keep the constraints (`keyvision.constraint_score` on
      the training frames, no ground truth). Reconstruction alone settles early where an autoencoder
      puts its keypoints, and not always on the joints: of three cart-pole seeds one put both
      keypoints on one point of the pole, and no later stage separated them (`docs/ablation.md`).
      Needs dynamics with constraints.
    - `candidate_runs`: the candidates are scored on at most this many training runs, every `k`-th
      run with `k = ceil(runs / candidate_runs)` (all runs when there are no more). Scoring encodes
      every frame of those runs once per candidate; on 450 runs of the cart-pole and the acrobot, the
      scores on every 9th run ranked the four candidates of each of three trainings as the scores on
      all runs did, at a ninth of the time (checked with the score's first form, before it was set
      against the keypoints' motion; with the current form, on the pendulum's two trainings too).
    - `rigid_steps`: steps of the rigid stage (0 leaves it out), between stage (a) and stage (b):
      the keypoints numbered after the constraints (`keyvision.assign_keypoints`), then the
      estimator and renderer trained further on single frames with stage (a)'s loss plus
      `rigid_weight * ConstraintDrift(pooled=True, relative=True)`. Stage (a) places keypoints by
      reconstruction alone, and nothing there asks a keypoint to sit on a joint: an acrobot's
      first keypoint slid from its elbow (hanging) to halfway up the first link (upright). Only
      the elbow keeps a fixed distance both to the pivot and to a point of the second link, so
      the relative drift of the scene's constraints, pooled over frames of many poses, has its
      minimum there (`docs/images.md`, "Control from frames"). Needs dynamics with constraints.
    - `rigid_weight`: the weight of the relative drift in the rigid stage (a squared relative
      spread of the lengths; stage (a)'s reconstruction error is about 1e-4 to 1e-3).
    - `dynamics_steps`: steps of stage (b), the dynamics alone fitted to the keypoints of the frozen
      estimator with `dynamics_loss`.
    - `dynamics_batch`: runs of keypoints per step of stage (b) (at most the number of runs).
    - `joint_steps`: steps of stage (c), everything trained with `Reconstruction() +
      heatmap_weight * HeatmapRegulariser() + dynamics_weight * h^4 * KeypointDynamics(dynamics_loss)`.
    - `joint_batch`, `window`: windows per step, and frames per window, of stage (c).
    - `refit_steps`: steps of stage (d), the dynamics alone fitted again, with `refit_loss`, to the
      keypoints of the estimator as stage (c) left it (its keypoints are far less noisy than those
      of stage (a), which the dynamics of stage (b) had to fit); `refit_batch` runs per step.
    - `refit_loss`: a cldyn loss, or `None` for `cldyn.MultipleShooting` over segments of about
      half a run (23 intervals of the paper's 50-frame runs): the predictions that the valid
      prediction time scores, from central-difference velocities.
    - `rounds`: how often stages (c) and (d) run, in turn; the later rounds are named `joint-2`,
      `refit-2`, ... The joint stage of the first round trains with `dynamics_loss`, those of the
      later rounds with `refine_loss` on dynamics that stage (d) has already fitted well.
    - `refine_loss`: a cldyn loss, or `None` for `cldyn.MultipleShooting` over the window
      (segments of `window - 3` intervals); `refine_weight` is its weight, times `h^4` as
      `dynamics_weight`.
    - `dynamics_loss`: a cldyn loss; `cldyn.Collocation()` (eq. 11-13) by default.
    - `dynamics_weight`: the weight `lambda` of the dynamics loss in stage (c), times `h^4` (`h` the
      frame interval). cldyn's dynamics losses are accelerations squared; keypoint noise `s` enters
      them as `s^2 / h^4`, so at a fixed weight the dynamics term would outweigh reconstruction 16
      times more at 100 frames per second than at 50. `h^4 L_d` is a squared position in the image
      frame, whatever the frame rate, and one weight serves every scene.
    - `heatmap_weight`: the weight of the heatmap regulariser (0 leaves it out, as the FC estimator
      needs).
    - `constraint_weight`: the weight of `keyvision.ConstraintDrift` in the joint stages (0 leaves
      it out; dynamics without constraints never have it): the variance of the constraint values of
      the keypoints along each window, a squared length in the image frame like `h^4 L_d`. It keeps
      the keypoints on rigid points of the bodies, which reconstruction alone does not.
    - `constraint_drift`: `"window"` (the variance along each window), `"pooled"` (over the whole
      batch, `ConstraintDrift(pooled=True)`: the lengths are the same in every run, which a
      keypoint that slides along its link with the pose breaks only across windows) or
      `"relative"` (pooled, each length's variance over its mean square,
      `ConstraintDrift(pooled=True, relative=True)`: scale-free, it gains nothing from drawing
      keypoints together).
    - `augment`: show the estimator every frame of the stages that train it (the candidates' trials,
      (a), the rigid stage and (c)) under a random dihedral transform (`keyvision.Augment`), its
      keypoints mapped back: trains an equivariant estimator.
    - `learning_rate`: Adam's peak learning rate for the networks in stage (a) (after element-wise
      gradient clipping at 5); `dynamics_learning_rate` for stages (b) and (d), `joint_learning_rate` for
      stage (c); with `None` (the default) `keyvision.train` chooses and records 1e-3 for dynamics with
      networks (`eqx.nn.Linear` layers), 1e-2 for those without (the structured model's few physical
      parameters: masses, gravity weights and gears move slowly at the networks' rate).
    - `warmup_steps`, `final_learning_rate`: every stage starts a fresh Adam, so its learning rate
      rises linearly from 0 over `warmup_steps` (at most a tenth of the stage) and then decays along
      a cosine to `final_learning_rate` times its peak at the stage's last step. Without the warm-up,
      Adam's first steps (each about the learning rate in size, whatever the gradient) undo much of
      what the previous stage learnt.
    - `log_every`, `checkpoint_every`: as in `cldyn.fit`, for every stage.

    !!! example

        ```python
        schedule = keyvision.Schedule(autoencoder_steps=3000, dynamics_steps=2000, joint_steps=1000)
        ```
    """

    autoencoder_steps: int = 2000
    autoencoder_batch: int = 64
    candidates: int = 1
    candidate_steps: int = 500
    candidate_runs: int = 50
    rigid_steps: int = 0
    rigid_weight: float = 0.01
    dynamics_steps: int = 2000
    dynamics_batch: int = 32
    joint_steps: int = 1000
    joint_batch: int = 8
    window: int = 10
    refit_steps: int = 2000
    refit_batch: int = 32
    refit_loss: cldyn.AbstractLoss | None = None
    rounds: int = 1
    refine_loss: cldyn.AbstractLoss | None = None
    refine_weight: float = 0.6
    dynamics_loss: cldyn.AbstractLoss = cldyn.Collocation()
    dynamics_weight: float = 60.0
    heatmap_weight: float = 0.1
    constraint_weight: float = 10.0
    constraint_drift: str = "window"
    augment: bool = False
    learning_rate: float = 1e-3
    dynamics_learning_rate: float | None = None
    joint_learning_rate: float = 3e-4
    warmup_steps: int = 100
    final_learning_rate: float = 0.1
    log_every: int = 50
    checkpoint_every: int = 500

    def __post_init__(self):
        for name in ("autoencoder_steps", "rigid_steps", "dynamics_steps", "joint_steps", "refit_steps"):
            check_positive(f"Schedule: {name}", getattr(self, name), integer=True, allow_zero=True)
        for name in ("autoencoder_batch", "candidates", "candidate_steps", "candidate_runs", "dynamics_batch",
                     "joint_batch", "refit_batch", "window", "rounds", "log_every", "checkpoint_every"):
            check_positive(f"Schedule: {name}", getattr(self, name), integer=True)
        for name in ("learning_rate", "dynamics_learning_rate", "joint_learning_rate", "final_learning_rate"):
            if name != "dynamics_learning_rate" or self.dynamics_learning_rate is not None:
                check_positive(f"Schedule: {name}", getattr(self, name))
        check_positive("Schedule: warmup_steps", self.warmup_steps, integer=True, allow_zero=True)
        if self.final_learning_rate > 1:
            raise ValueError(
                "Schedule: final_learning_rate is a fraction of the peak, at most 1; got "
                f"{self.final_learning_rate}"
            )
        weights = ("dynamics_weight", "refine_weight", "heatmap_weight", "constraint_weight", "rigid_weight")
        for name in weights:
            check_positive(f"Schedule: {name}", getattr(self, name), allow_zero=True)
        if self.constraint_drift not in ("window", "pooled", "relative"):
            raise ValueError(
                "Schedule: constraint_drift must be 'window', 'pooled' or 'relative', got "
                f"{self.constraint_drift!r}"
            )
        if not isinstance(self.augment, bool):
            raise TypeError(f"Schedule: augment must be True or False, got {self.augment!r}")
        if not isinstance(self.dynamics_loss, cldyn.AbstractLoss):
            raise TypeError(f"Schedule: dynamics_loss must be a cldyn loss, got {self.dynamics_loss!r}")
        for name in ("refit_loss", "refine_loss"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, cldyn.AbstractLoss):
                raise TypeError(f"Schedule: {name} must be a cldyn loss or None, got {value!r}")
        if self.rounds > 1 and self.refine_loss is None and self.window < 4:
            raise ValueError(
                f"Schedule: multiple shooting over windows of {self.window} frames needs at least 4"
            )

    def describe(self) -> dict:
        """The schedule as JSON-able values (the loss as its description)."""
        described = dataclasses.asdict(self)
        described["dynamics_loss"] = eqx.tree_pformat(self.dynamics_loss)
        for name in ("refit_loss", "refine_loss"):
            value = getattr(self, name)
            described[name] = None if value is None else eqx.tree_pformat(value)
        return described


NETWORKS_DYNAMICS_LR = 1e-3  # the dynamics stages' peak learning rate for dynamics with networks
PHYSICAL_DYNAMICS_LR = 1e-2  # ... and for dynamics without any (physical parameters only)


def for_dynamics(schedule: Schedule, dynamics) -> Schedule:
    """`schedule` with its `dynamics_learning_rate` chosen for `dynamics` where it is `None`:
    `NETWORKS_DYNAMICS_LR` if they hold an `eqx.nn.Linear` layer, `PHYSICAL_DYNAMICS_LR` if not."""
    if schedule.dynamics_learning_rate is not None:
        return schedule
    is_linear = lambda node: isinstance(node, eqx.nn.Linear)  # noqa: E731
    networks = any(is_linear(node) for node in jax.tree.leaves(dynamics, is_leaf=is_linear))
    rate = NETWORKS_DYNAMICS_LR if networks else PHYSICAL_DYNAMICS_LR
    return dataclasses.replace(schedule, dynamics_learning_rate=rate)


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """What `keyvision.train` returns.

    **Fields:**

    - `model`: the trained `KeyCLD`.
    - `stages`: the `cldyn.FitResult` of every stage that ran, by name (`"autoencoder"`,
      `"dynamics"`, `"joint"`, `"refit"`, ...), with its history and settings (the key of each stage
      among them).
    - `keypoint_order`: how `keyvision.assign_keypoints` renumbered the keypoints of stage (a)
      (keypoint `k` is the autoencoder's keypoint `keypoint_order[k]`), or `None` if it did not run.
    - `candidates`: with `Schedule.candidates` above 1, the candidates' trial stages, their
      `keyvision.constraint_score` and the stage chosen (`{"stages", "scores", "chosen", "runs"}`, `runs`
      the number of training runs scored); else `None`.
    """

    model: KeyCLD
    stages: dict
    keypoint_order: tuple[int, ...] | None = None
    candidates: dict | None = None


def _stage_keypoints(
    model: KeyCLD,
    data: ImageSequences,
    validation: ImageSequences | None,
    out: pathlib.Path | None,
    stage: str,
    resume: bool,
) -> tuple[cldyn.Sequences, cldyn.Sequences | None]:
    """The keypoints that a dynamics stage fits (`encode_sequences` of the training and validation
    frames), kept in `out/keypoints-<stage>.npz` and read back from there on resume.

    A GPU need not encode the same frames bitwise alike in two processes (its convolutions are
    autotuned afresh), and `cldyn.fit` resumes a checkpoint only on the data it was written with:
    re-encoded keypoints would refuse every resume past stage (b) there. A stage without a checkpoint
    yet encodes afresh (whatever an earlier training left in `out`).
    """
    path = None if out is None else out / f"keypoints-{stage}.npz"
    # only a stage that has checkpointed was fitted to them: any other starts on fresh keypoints
    started = path is not None and fit_files(out, stage)["checkpoint"].exists()
    if resume and started and path.is_file():
        try:
            stored = read_npz(path)
            schema, x, x_validation = str(stored["schema"]), stored["x"], stored.get("validation")
        except (ValueError, KeyError) as error:
            problem = str(error).removeprefix(f"{path}: ")
            raise cldyn.CheckpointError(
                f"{path}: unreadable ({type(error).__name__}: {problem}); it holds the keypoints that the "
                f"checkpoint of stage {stage!r} was fitted to: delete it and checkpoint-{stage}.eqx to "
                "run that stage afresh"
            ) from None
        expected = (data.num_runs, data.num_samples)
        validation_expected = None if validation is None else (validation.num_runs, validation.num_samples)
        if (
            schema != _KEYPOINTS_SCHEMA
            or x.ndim != 3
            or x.shape[:2] != expected
            or (None if x_validation is None else x_validation.shape[:2]) != validation_expected
        ):
            raise cldyn.CheckpointError(
                f"{path}: keypoints of {x.shape[:2]} runs x frames for this training's {expected} "
                f"(validation {None if x_validation is None else x_validation.shape[:2]} for "
                f"{validation_expected}): written by another training"
            )

        def sequences(frames, values):
            return cldyn.Sequences(jnp.asarray(values), jnp.asarray(frames.u).astype(values.dtype), frames.dt)

        return sequences(data, x), None if validation is None else sequences(validation, x_validation)
    keypoints = encode_sequences(model, data)
    validation_keypoints = None if validation is None else encode_sequences(model, validation)
    if path is not None:
        arrays = {"schema": np.asarray(_KEYPOINTS_SCHEMA), "x": np.asarray(keypoints.x)}
        if validation_keypoints is not None:
            arrays["validation"] = np.asarray(validation_keypoints.x)
        atomic_save(path, lambda temporary: np.savez(temporary, **arrays))
    return keypoints, validation_keypoints


def stage_names(round_: int) -> tuple[str, str]:
    """The names of the joint and refit stages of a round (1, 2, ...): `joint`, `refit`, then
    `joint-2`, `refit-2`, ..."""
    suffix = "" if round_ == 1 else f"-{round_}"
    return f"joint{suffix}", f"refit{suffix}"


def candidate_stages(count: int) -> list[str]:
    """The names of the trial stages of `count` candidates: none for one, else `candidate-1`, ..."""
    return [f"candidate-{k}" for k in range(1, count + 1)] if count > 1 else []


def stages_run(schedule: dict) -> list[str]:
    """The names of the stages that a schedule (`Schedule.describe()`) runs, in order."""
    names = candidate_stages(int(schedule.get("candidates", 1))) if schedule.get("autoencoder_steps") else []
    names += [name for name in ("autoencoder", "rigid", "dynamics") if schedule.get(f"{name}_steps")]
    for round_ in range(1, int(schedule.get("rounds", 1)) + 1):
        joint, refit = stage_names(round_)
        names += [joint] if schedule.get("joint_steps") else []
        names += [refit] if schedule.get("refit_steps") else []
    return names


def _stage_key(key, stage: str):
    # the first three stages keep the keys they always had (a split of `key` in three); the others
    # fold their number into it
    if stage in _STAGES:
        return jax.random.split(key, 3)[_STAGES.index(stage)]
    if stage == "rigid":
        return jax.random.fold_in(key, 1)  # the rounds fold in 2 and up
    name, _, number = stage.partition("-")
    if name == "candidate":
        return jax.random.fold_in(jax.random.fold_in(key, 0), int(number))
    round_ = int(number) if number else 1
    return jax.random.fold_in(key, 2 * round_ + (1 if name == "refit" else 0))


def _networks_only(model: KeyCLD):
    spec = jax.tree.map(eqx.is_inexact_array, model)
    return eqx.tree_at(lambda m: m.dynamics, spec, replace=False)


def _adam(schedule: Schedule, peak: float, steps: int) -> optax.GradientTransformation:
    warmup = min(schedule.warmup_steps, steps // 10)
    return _clipped_adam(peak, warmup, max(steps, warmup + 1), peak * schedule.final_learning_rate)


@functools.cache
def _clipped_adam(peak: float, warmup: int, steps: int, end: float) -> optax.GradientTransformation:
    # one object per setting: the compiled steps take the optimiser as a static argument, so a fresh
    # (equal but not identical) one would compile every stage again on each call of `train`
    rate = optax.warmup_cosine_decay_schedule(0.0, peak, warmup, steps, end_value=end)
    return optax.chain(optax.clip(5.0), optax.adam(rate))


def _key_data(key) -> list[int]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return [int(v) for v in np.asarray(key).reshape(-1)]


def train(
    model: KeyCLD | Sequence[KeyCLD],
    data: ImageSequences,
    *,
    key: PRNGKeyArray,
    schedule: Schedule = Schedule(),
    validation: ImageSequences | None = None,
    out: "str | os.PathLike | None" = None,
    resume: bool = False,
    progress_meter: cldyn.AbstractProgressMeter = cldyn.NoProgressMeter(),
    devices: Sequence[jax.Device] | None = None,
    loop: cldyn.AbstractStepLoop | None = None,
) -> TrainResult:
    """Train a KeyCLD model on frames, unsupervised, in four stages of `cldyn.fit`.

    1. `"autoencoder"`: the estimator and the renderer on single frames (reconstruction, eq. 10,
       plus the heatmap regulariser); the dynamics are frozen. With `schedule.candidates` above 1
       it starts from the best of several candidates after a short trial of each (see `Schedule`).
       With `schedule.rigid_steps`, then
       `"rigid"`: the keypoints numbered after the constraints (`keyvision.assign_keypoints`) and the
       networks trained further with the relative constraint drift added (see `Schedule`).
    2. `"dynamics"`: the frames are encoded once by the frozen estimator
       (`keyvision.encode_sequences`) and the dynamics model is fitted to the keypoints with
       `schedule.dynamics_loss` (collocation, eq. 11-13: seconds, no images involved).
    3. `"joint"`: everything on windows of `schedule.window` frames with
       $L = L_r + \\lambda L_d$ (plus the regularisers: heatmaps and `keyvision.ConstraintDrift`),
       $L_d$ on the encoded keypoints.
    4. `"refit"`: the frames are encoded again and the dynamics alone are fitted to the new
       keypoints with `schedule.refit_loss` (multiple shooting by default).

    Each stage is one `fit` with its own key (split from `key`) and its own files in `out`
    (`checkpoint-<stage>.eqx`, `history-<stage>.json`, `model-<stage>.eqx`; the dynamics stages also
    `keypoints-<stage>.npz`, the encoded keypoints they fit), float32, the batch sharded over
    `devices`. With `resume=True` a restarted call skips the finished stages and resumes the
    interrupted one bitwise, on the keypoints it started with (a GPU need not encode the frames
    bitwise alike twice). `out/train.json` records the key and the schedule (with the dynamics'
    learning rate as chosen).

    **Arguments:**

    - `model`: the `keyvision.KeyCLD` to train, or a sequence of `schedule.candidates` of them
      (the same networks from different keys) to choose from.
    - `data`: the training `keyvision.ImageSequences`.
    - `key`: a `jax.random` key for the batches.
    - `schedule`: a `keyvision.Schedule` (steps, batches, weights, learning rates).
    - `validation`: held-out `ImageSequences` whose loss is recorded at every validation point;
      keep it small (a few runs): it is evaluated in one call.
    - `out`: the output directory, or `None` to write nothing.
    - `resume`: continue from the checkpoints in `out`.
    - `progress_meter`: e.g. `cldyn.TextProgressMeter()`.
    - `devices`: the devices to shard the batch over (all local devices by default).
    - `loop`: how the stages of images (the candidates' trials, (a), rigid and joint) run their
      steps: `cldyn.HostLoop()` by default, one compiled step dispatched at a time, since XLA's CPU
      backend runs convolutions inside a compiled loop several times slower
      (`benchmarks/fit_loop.py`); `cldyn.CompiledLoop()` compiles each chunk of steps as one loop,
      for a device that the dispatch from Python leaves idle. The same steps and batches either
      way. The dynamics stages always run compiled.

    **Returns:** a `keyvision.TrainResult` with the model and each stage's `cldyn.FitResult`.

    !!! example

        ```python
        train, validation = keyvision.render("keycld/pendulum").split()
        result = keyvision.train(model, keyvision.ImageSequences.from_frames(train),
                                 key=jax.random.key(0), out="runs/pendulum", resume=True,
                                 progress_meter=cldyn.TextProgressMeter())
        ```
    """
    if not isinstance(schedule, Schedule):
        raise TypeError(f"train: schedule must be a keyvision.Schedule, got {type(schedule).__name__}")
    models = list(model) if isinstance(model, Sequence) else [model]
    for candidate in models:
        if not isinstance(candidate, KeyCLD):
            raise TypeError(f"train: model must be a keyvision.KeyCLD, got {type(candidate).__name__}")
    if len(models) != schedule.candidates:
        raise ValueError(f"train: {len(models)} models given for Schedule.candidates = {schedule.candidates}")
    model = models[0]
    if not isinstance(data, ImageSequences):
        raise TypeError(f"train: data must be keyvision.ImageSequences, got {type(data).__name__}")
    needs = (("the rigid stage", "rigid_steps", schedule.rigid_steps > 0),
             ("choosing among candidates", "candidates", schedule.candidates > 1))
    for what, name, used in needs:
        if used and getattr(model.dynamics, "constraint", None) is None:
            raise ValueError(
                f"train: {what} (Schedule.{name} = {getattr(schedule, name)}) needs dynamics with "
                f"constraints, got {type(model.dynamics).__name__} without any"
            )
    if schedule.candidates > 1 and not schedule.autoencoder_steps:
        raise ValueError("train: Schedule.candidates chooses among autoencoders: it needs autoencoder_steps")
    schedule = for_dynamics(schedule, model.dynamics)
    keys = dict(zip(_STAGES, jax.random.split(key, 3)))
    if out is not None:
        out = pathlib.Path(out)
        out.mkdir(parents=True, exist_ok=True)
        record = {"schema": _SCHEMA, "key": _key_data(key), "schedule": schedule.describe()}
        atomic_write(out / "train.json", json.dumps(record, indent=1))
    # XLA's CPU backend runs convolutions inside a compiled loop several times slower than outside
    # one: by default the stages with networks of images dispatch one compiled step at a time
    if loop is not None and not isinstance(loop, cldyn.AbstractStepLoop):
        raise TypeError(f"train: loop must be a cldyn step loop (HostLoop, CompiledLoop), got {loop!r}")
    images_loop = cldyn.HostLoop() if loop is None else loop
    common = {
        "out": out,
        "resume": resume,
        "progress_meter": progress_meter,
        "devices": devices,
        "log_every": schedule.log_every,
        "validate_every": schedule.checkpoint_every,
        "checkpoint_every": schedule.checkpoint_every,
    }
    images_loss = Reconstruction()
    if schedule.heatmap_weight > 0:
        images_loss = images_loss + schedule.heatmap_weight * HeatmapRegulariser()
    windows_loss = images_loss
    if schedule.constraint_weight > 0 and getattr(model.dynamics, "constraint", None) is not None:
        drift = ConstraintDrift(
            pooled=schedule.constraint_drift != "window", relative=schedule.constraint_drift == "relative"
        )
        windows_loss = windows_loss + schedule.constraint_weight * drift
    stages = {}

    def frames_batching(batch_size: int, length: int) -> cldyn.AbstractBatching:
        windows = cldyn.Windows(batch_size, length)
        return Augment(windows) if schedule.augment else windows

    def networks_fit(model: KeyCLD, stage: str, loss, steps: int, stage_key) -> cldyn.FitResult:
        # the stages of single frames that train the networks alone: trials, (a) and rigid
        stages[stage] = cldyn.fit(
            model, data, loss=loss, steps=steps, key=stage_key,
            optimizer=_adam(schedule, schedule.learning_rate, steps),
            batching=frames_batching(schedule.autoencoder_batch, 1),
            validation=validation, trainable=_networks_only, stage=stage, loop=images_loop, **common,
        )
        return stages[stage].model

    chosen = None
    if schedule.candidates > 1:
        trials = candidate_stages(schedule.candidates)
        for stage, candidate in zip(trials, models):
            networks_fit(candidate, stage, images_loss, schedule.candidate_steps, _stage_key(key, stage))
        fits = {stage: stages[stage] for stage in trials}
        chosen = choose_candidate(fits, data, out, resume, progress_meter, runs=schedule.candidate_runs)
        model = stages[chosen["chosen"]].model
    if schedule.autoencoder_steps:
        steps = schedule.autoencoder_steps
        model = networks_fit(model, "autoencoder", images_loss, steps, keys["autoencoder"])

    order = None
    if schedule.rigid_steps:
        model, order = rigid_order(model, data, out, resume)
        rigid_loss = images_loss + schedule.rigid_weight * ConstraintDrift(pooled=True, relative=True)
        model = networks_fit(model, "rigid", rigid_loss, schedule.rigid_steps, _stage_key(key, "rigid"))

    if schedule.dynamics_steps:
        keypoints, validation_keypoints = _stage_keypoints(model, data, validation, out, "dynamics", resume)
        # after the rigid stage the estimator already gives its keypoints in the constraints' order
        renumber = order is None
        if renumber:
            model, order = assign_and_record(model, keypoints, out)
        index = np.asarray([2 * k + c for k in order for c in (0, 1)])

        def ordered(sequences):
            if sequences is None or not renumber:
                return sequences
            return cldyn.Sequences(sequences.x[..., index], sequences.u, sequences.dt)

        keypoints = ordered(keypoints)
        stages["dynamics"] = cldyn.fit(
            model.dynamics, keypoints, loss=schedule.dynamics_loss, steps=schedule.dynamics_steps,
            key=keys["dynamics"],
            optimizer=_adam(schedule, schedule.dynamics_learning_rate, schedule.dynamics_steps),
            batching=cldyn.Runs(min(schedule.dynamics_batch, keypoints.num_runs)),
            validation=ordered(validation_keypoints),
            stage="dynamics", **common,
        )
        model = eqx.tree_at(lambda m: m.dynamics, model, stages["dynamics"].model)

    refit_loss = schedule.refit_loss
    if refit_loss is None:
        refit_loss = cldyn.MultipleShooting(segment=max(1, (data.num_samples - 3) // 2))
    refine_loss = schedule.refine_loss
    if refine_loss is None:
        refine_loss = cldyn.MultipleShooting(segment=max(1, schedule.window - 3))
    for round_ in range(1, schedule.rounds + 1):
        joint, refit = stage_names(round_)
        if schedule.joint_steps:
            dynamics_loss, weight = (
                (schedule.dynamics_loss, schedule.dynamics_weight)
                if round_ == 1
                else (refine_loss, schedule.refine_weight)
            )
            stages[joint] = cldyn.fit(
                model, data, loss=windows_loss + weight * data.dt**4 * KeypointDynamics(dynamics_loss),
                steps=schedule.joint_steps, key=_stage_key(key, joint),
                optimizer=_adam(schedule, schedule.joint_learning_rate, schedule.joint_steps),
                batching=frames_batching(schedule.joint_batch, schedule.window),
                validation=validation, stage=joint, loop=images_loop, **common,
            )
            model = stages[joint].model
        if schedule.refit_steps:
            keypoints, validation_keypoints = _stage_keypoints(model, data, validation, out, refit, resume)
            stages[refit] = cldyn.fit(
                model.dynamics, keypoints, loss=refit_loss, steps=schedule.refit_steps,
                key=_stage_key(key, refit),
                optimizer=_adam(schedule, schedule.dynamics_learning_rate, schedule.refit_steps),
                batching=cldyn.Runs(min(schedule.refit_batch, keypoints.num_runs)),
                validation=validation_keypoints,
                stage=refit, **common,
            )
            model = eqx.tree_at(lambda m: m.dynamics, model, stages[refit].model)
    return TrainResult(model=model, stages=stages, keypoint_order=order, candidates=chosen)

