"""Finding what a model learnt from images is missing: its keypoints as joints (`_joints.py`),
`cldyn.identify`, and the effects' values in MuJoCo's units."""

import dataclasses
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

import cldyn

from ._balance import add_checked_balance, balance_entry
from ._controls import _place_controls
from ._data import ImageSequences
from ._evaluate import json_number, predict_runs, prediction_threshold, valid_prediction_time
from ._joints import JointStructure, model_joints
from ._model import KeyCLD
from ._train import Schedule, encode_sequences, train


def energy_scale(
    model: cldyn.ConstrainedLagrangian,
    structure: JointStructure,
    x: Float[ArrayLike, "N k"],
    gears: Mapping[str, float],
    metres_per_unit: float,
) -> dict:
    """Joules per unit of a learnt model's energy, from the actuators' known gears.

    A model learnt from images sets its own energy unit (the equations of motion are homogeneous in
    mass, potential and input gain). Its generalized force per unit control at an actuated joint,
    $(G^T B(x))_{jj}$ with $G = dF/dq$, against the actuator's gear $g_j$ (newton-metres, or newtons
    for a slide, per unit control) fixes it: $\\kappa = g_j s_j / (G^T B)_{jj}$, with $s_j$ the
    metres per keypoint unit for a slide (1 for a hinge). The median over the samples, then of the
    magnitudes over the actuated joints (a hinge's sign is its angle's sense against MuJoCo's).

    **Returns:** a dict with `joules_per_unit`, per actuated joint its own (signed) estimate, and
    `spread`, the largest magnitude over the smallest: about 1 for a model calibrated in energy
    across its joints; far from 1, values converted with it are not to be trusted.
    """
    x = jnp.asarray(x)
    if getattr(model, "input_matrix", None) is None:
        raise ValueError("energy_scale: the model has no input matrix")
    q = jax.vmap(structure.joint_map.inverse)(x)
    g = jax.vmap(jax.jacfwd(structure.joint_map.forward))(q)  # dx/dq: (N, k, m)
    b = jax.vmap(model.input_matrix)(x)  # (N, k, l)
    per_joint = {}
    gain = np.asarray(jnp.einsum("nkm,nkl->nml", g, b))  # generalized force at joint m per control l
    for name, gear in gears.items():
        if name not in structure.names:
            continue
        j = structure.names.index(name)
        s = metres_per_unit if structure.kinds[j] == "slide" else 1.0
        column = int(np.argmax(np.abs(np.median(gain[:, j, :], axis=0))))
        per_joint[name] = float(gear * s / np.median(gain[:, j, column]))
    if not per_joint:
        raise ValueError("energy_scale: no actuated joint among the structure's joints")
    # a hinge's estimate carries the sign of its angle's sense against MuJoCo's: the magnitudes agree
    magnitudes = np.abs(list(per_joint.values()))
    return {
        "joules_per_unit": float(np.median(magnitudes)),
        "per_joint": per_joint,
        "spread": float(magnitudes.max() / magnitudes.min()),
    }


# value in MuJoCo's units = value in the model's units * joules_per_unit * metres_per_unit ** power,
# the power for a slide joint (a hinge's angle is the same in both)
_POWERS = {
    "joint_damping": -2,  # force per velocity
    "joint_quadratic_damping": -3,  # force per velocity squared
    "joint_coulomb": -1,  # force
    "joint_spring": -2,  # force per displacement
    "joint_armature": -2,  # mass
}


def metres_per_unit(camera) -> float:
    """Metres in the plane of motion per unit of the image frame, at the image centre (the mean of
    the two directions): what turns a keypoint length into metres."""
    step = 1e-3
    centre = camera.to_plane(np.zeros(2))
    along = [np.linalg.norm(camera.to_plane(np.asarray(d) * step) - centre) / step for d in ((1, 0), (0, 1))]
    return float(np.mean(along))


def actuator_gears(mjcf_xml: str) -> dict[str, float]:
    """Joint name -> the gear of the motor that drives it (newton-metres or newtons per unit control)."""
    from ._scene import _mujoco

    mujoco = _mujoco()
    model = mujoco.MjModel.from_xml_string(mjcf_xml)
    gears = {}
    for a in range(model.nu):
        if int(model.actuator_trntype[a]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            continue
        joint = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(model.actuator_trnid[a, 0]))
        gears[joint] = float(model.actuator_gear[a, 0])
    return gears


@dataclasses.dataclass(frozen=True)
class ImageIdentification:
    """What `keyvision.identify` found, in the model's units and in MuJoCo's.

    **Fields:**

    - `identification`: `cldyn.identify`'s result on the estimated keypoints (its report, errors and
      plots, in the model's units: keypoints in the image frame, the model's energy unit).
    - `effects`: one dict per detected effect: `name`, `where` (the joint), `value` and `ci` in
      MuJoCo's units (`None` where no conversion applies), `value_model` and `ci_model` in the model's,
      and `source`: `"force residual"` (`cldyn.identify`) or `"energy balance"` (`add_balance`).
    - `structure`: the `JointStructure` of the keypoints.
    - `joules_per_unit`, `metres_per_unit`: the conversions (`energy_scale`, `metres_per_unit`). An
      effect at an actuated joint converts with that joint's own energy scale (its motor's gear), any
      other with `joules_per_unit`.
    - `energy_spread`: how far the actuated joints' own energy scales disagree (`energy_scale`'s
      `spread`, 1 for one actuated joint): far from 1, the values in MuJoCo's units are unreliable.
    - `model`: the KeyCLD model with the effects added and the dynamics refitted (float64 dynamics);
      with `add_balance`, the balance's damping that passed the held-out rollout test added after the
      refit.
    - `images`: on the frames' validation runs (left out of the identification), the VPT (mean and
      median), the image MSE over all their frames and its mean over the runs frame by frame
      (`mse_over_time`) of the model `before` and `after` (and `refined`, with `refine`), with the
      VPT `threshold` and `dt`; `None` without validation runs.
    - `refined`: with `refine`, the model after the joint stage with the image losses (float32);
      `None` otherwise.
    - `balance`: with `balance`, one dict per joint from `cldyn.energy_balance` on the same keypoints
      and model: `where`, the viscous damping the model lacks there by the balance of energy (`value`,
      `ci`: MuJoCo's units; `value_model`, `ci_model`: the model's) and `detected` (its interval above
      zero). A check beside the detections, which errors of the learnt inertia and potential do not
      bias; it adds to `model` only with `add_balance`.
    """

    identification: object
    effects: tuple[dict, ...]
    structure: JointStructure
    joules_per_unit: float
    metres_per_unit: float
    model: object
    images: dict | None = None
    energy_spread: float = 1.0
    refined: object = None
    balance: tuple[dict, ...] = ()


def _joules_at(where: str, scale: dict) -> float:
    """The energy scale that converts an effect at joint `where`: that joint's own, from its motor's
    gear, where it is actuated (a force at a joint and the motor's force there are compared in the
    same direction, whatever the learnt model's calibration elsewhere); the median over the actuated
    joints otherwise."""
    own = scale["per_joint"].get(where)
    return abs(own) if own is not None else scale["joules_per_unit"]


def _convert(name: str, kind: str, value: float, joules: float, metres: float) -> float | None:
    if name == "actuator_gain":
        return value  # a ratio of gains: no unit
    if name not in _POWERS:
        return None
    return value * joules * (metres ** _POWERS[name] if kind == "slide" else 1.0)


def identify(
    model,
    frames,
    *,
    inputs=None,
    refine=None,
    balance=True,
    add_balance=False,
    progress_meter=None,
    **options,
) -> ImageIdentification:
    """Find the effects that a KeyCLD model learnt from images is missing, from frames of the system.

    The frames are encoded by the model's estimator; the keypoints' constraints give the joints
    (`keyvision.joint_structure`, named after the scene's MuJoCo joints; `keyvision.scene_joints` for
    constraints whose geometry only the scene gives); `cldyn.identify` runs with
    the learnt dynamics as the nominal model, in float64; the detected effects are converted to
    MuJoCo's units with the camera's scale (`metres_per_unit`) and the energy scale fixed by the
    scene's actuator gears (`energy_scale`). What can be identified from images: effects at the joints
    (damping, Coulomb friction, springs, armature) and actuator gains, as far as the keypoints resolve
    the motion; not the absolute masses (the learnt energy unit is set by the gears, so a mass is
    only known relative to the others).

    **Arguments:**

    - `model`: a `keyvision.KeyCLD` whose dynamics are a `ConstrainedLagrangian`: with a planar chain
      of constraints (KeyCLD's scenes), or the constraints of the frames' scene
      (`keyvision.scene_constraint`, any tree of hinges and slides that `cldyn.mujoco.from_mjcf` reads),
      whose joints are then the scene's (`keyvision.scene_joints`), read on its keypoints moved along
      their rays to the scene's lengths where a pivot, a rod or a hinge whose anchor is no keypoint
      keeps them at their own; a distance kept near zero (a keypoint drawn onto its pivot) is
      refused, naming the constraint.
    - `frames`: `keyvision.Frames` of the real system, rendered from a MuJoCo scene
      (`frames.info["mjcf_xml"]` names the joints and gives the gears): the training runs are
      identified, the validation runs score the model before and after in images (VPT, MSE).
    - `inputs`: the name of the actuator behind each of the model's inputs, in order (those of the
      scene it was trained on, e.g. `("shoulder", "elbow")`; `scene_actuators` reads them). The
      frames' controls are then placed by actuator name, and an input whose actuator the frames'
      scene lacks is held at zero: dm_control's stock acrobot drives the elbow only. `None`
      (default): the frames have one control per input, in the model's order.
    - `refine`: a `keyvision.Schedule` for a last step: the model with the effects added trained
      jointly with the image losses (stage (c) of `keyvision.train`: its `joint_*`, `window` and weight
      fields) on the identified runs' frames; its other stages are not run. `None` (default): the
      dynamics refit of `cldyn.identify` only.
    - `balance`: also measure each joint's missing viscous damping by `cldyn.energy_balance` on the
      same keypoints (instrumental variables, identify's window, the velocities smoothed in the
      joint coordinates of the keypoints' structure), converted as the detections are.
      `cldyn.identify`'s force residual carries the learnt model's errors of inertia and potential at
      every sample, which can be larger than a damping's force; the balance cannot be fooled by
      them. It is reported beside the detections (`ImageIdentification.balance`).
    - `add_balance`: also add to the model, as a `cldyn.JointDamping`, the damping the balance finds
      at each joint whose interval lies above zero and where no damping was detected (an effect with
      `"source": "energy balance"`), before the image scores and `refine`, where it passes the test
      `cldyn.identify` puts to its own detections: it must lower the keypoints' held-out rollout error
      on identify's held-out runs (each joint's against the others' alone, then all against none);
      a joint that does not is named in the warnings and not added.
    - `progress_meter`: a `cldyn.AbstractProgressMeter`.
    - `options`: passed on to `cldyn.identify` (`effects`, `criteria`, `seed`, ...). The learnt
      potential is held fixed in the refit (`refit_potential=False`) unless given otherwise.

    **Returns:** a `keyvision.ImageIdentification`. Needs JAX's 64-bit mode
    (as the `keyvision identify` command turns on, and `cldyn.identify` needs); without it a
    `ValueError` says so.
    """
    if jax.dtypes.canonicalize_dtype(jnp.float64) != jnp.float64:
        raise ValueError("identify runs in float64: turn on JAX's 64-bit mode first")
    if add_balance and not balance:
        raise ValueError("identify: add_balance needs balance=True")
    if not isinstance(model, KeyCLD) or not isinstance(model.dynamics, cldyn.ConstrainedLagrangian):
        raise TypeError("identify: model must be a keyvision.KeyCLD with ConstrainedLagrangian dynamics")
    xml = frames.info.get("mjcf_xml")
    if not xml:
        raise ValueError("identify: the frames carry no MuJoCo scene (frames.info['mjcf_xml'])")
    frames = _place_controls(frames, inputs, model.dynamics.num_inputs)
    measured, held_out = frames.split()
    if measured.num_runs == 0:
        raise ValueError(f"identify: all {frames.num_runs} runs of the frames are validation runs")
    x = np.asarray(encode_sequences(model, ImageSequences.from_frames(measured)).x, dtype=np.float64)
    dynamics = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, model.dynamics)
    names = list(frames.info.get("joint_names", []))
    structure = model_joints(dynamics.constraint, x, frames, names if len(names) else None)
    # an estimated keypoint is not exactly a rigid point of its body (it slides by a fraction of a
    # pixel with the pose, which identify's constraint check rejects as a wrong model): the joints
    # read from the keypoints place a rigid chain of the measured lengths, x = F(q(x))
    flat = jnp.asarray(x.reshape(-1, x.shape[-1]))
    rigid = jax.vmap(lambda y: structure.joint_map.forward(structure.joint_map.inverse(y)))(flat)
    x = np.asarray(rigid).reshape(x.shape)
    data = cldyn.Sequences(x, np.asarray(measured.u, dtype=np.float64), frames.dt)
    if progress_meter is not None:
        options["progress_meter"] = progress_meter
    # the learnt potential was learnt from every frame of the training data; refitted on these runs it
    # fits them at the expense of other motions (measured: the held-out frames predicted worse)
    options.setdefault("refit_potential", False)
    actuators = inputs if inputs is not None else frames.info.get("actuator_names", [])
    options.setdefault("actuator_names", [str(name) for name in actuators] or None)
    result = cldyn.identify(
        dynamics, data, joint_coordinates=structure.coordinates, joints=structure.joint_map, **options
    )
    metres = metres_per_unit(frames.camera)
    scale = energy_scale(dynamics, structure, x.reshape(-1, x.shape[-1]), actuator_gears(xml), metres)
    joules = scale["joules_per_unit"]
    effects = []
    for d in result.detected:
        where = d.candidate.where
        kind = structure.kinds[structure.names.index(where)] if where in structure.names else ""
        at = _joules_at(where, scale)
        value = _convert(d.name, kind, d.value, at, metres)
        ci = None if value is None else tuple(_convert(d.name, kind, c, at, metres) for c in d.ci)
        effects.append(
            {
                "name": d.name,
                "where": d.candidate.where,
                "value": value,
                "ci": ci,
                "value_model": float(d.value),
                "ci_model": tuple(float(c) for c in d.ci),
                "source": "force residual",
            }
        )
    balanced = ()
    if balance:
        seed = options.get("seed", 0)
        found = cldyn.energy_balance(
            dynamics, data, joint_coordinates=structure.coordinates, joints=structure.joint_map, seed=seed
        )

        def convert(where, kind, value):
            return _convert("joint_damping", kind, value, _joules_at(where, scale), metres)

        balanced = tuple(balance_entry(found, j, structure, convert) for j in range(len(found.joint_names)))
    dynamics_after = result.model
    if add_balance:
        dynamics_after, added, notes = add_checked_balance(
            dynamics_after,
            balanced,
            effects,
            structure,
            data,
            result.settings["held_out_runs"],
            options.get("smoothing"),
        )
        effects += added
        result = dataclasses.replace(result, warnings=tuple(result.warnings) + tuple(notes))
    augmented = KeyCLD(model.estimator, dynamics_after, model.renderer)
    refined = None
    if refine is not None:
        refined = _refine(augmented, ImageSequences.from_frames(measured), refine, options.get("seed", 0))
    images = _image_errors(model, augmented, held_out, refined) if held_out.num_runs else None
    return ImageIdentification(
        result,
        tuple(effects),
        structure,
        joules,
        metres,
        augmented,
        images,
        scale["spread"],
        refined,
        balanced,
    )


def _single(model):
    return jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, model)


def _refine(model, data, schedule, seed: int):
    """The joint stage of `keyvision.train` alone, on `data`, from `model` (float32)."""
    if not isinstance(schedule, Schedule):
        raise TypeError(f"identify: refine must be a keyvision.Schedule, got {type(schedule).__name__}")
    if not schedule.joint_steps:
        raise ValueError("identify: refine's schedule has joint_steps=0: nothing to refine")
    stage = dataclasses.replace(schedule, autoencoder_steps=0, dynamics_steps=0, refit_steps=0, rounds=1)
    return train(_single(model), data, key=jax.random.key(seed), schedule=stage).model


def _image_errors(before, after, validation, refined=None) -> dict:
    """VPT and image MSE of the model before and after (and refined), predicting the validation runs
    (float32)."""
    images = validation.images(np.float32)
    controls = validation.u.astype(np.float32)
    threshold = prediction_threshold(images)
    record = {"runs": validation.num_runs, "threshold": threshold, "dt": validation.dt}
    models = {"before": before, "after": after, **({} if refined is None else {"refined": refined})}
    for name, model in models.items():
        model = _single(model)
        keypoints, predicted = predict_runs(model, images, controls, validation.dt)
        vpt = np.asarray(valid_prediction_time(predicted, images, threshold=threshold))
        # NaN (null in JSON) over the frames where a run's prediction failed: no error to average
        per_frame = np.mean((predicted - images) ** 2, axis=(0, 2, 3, 4))
        record[name] = {
            "vpt": {"mean": float(vpt.mean()), "median": float(np.median(vpt))},
            "mse": json_number(per_frame.mean()),
            "mse_over_time": [json_number(v) for v in per_frame],
            "failed_runs": np.flatnonzero(~np.all(np.isfinite(keypoints), axis=(-2, -1))).tolist(),
        }
    return record


def joint_stage(recipe: dict, steps: int) -> Schedule:
    """The joint stage (c) of a training recipe (`keyvision.json`'s `schedule`), for `steps` steps and
    nothing else: what `keyvision.identify(refine=)` runs after adding effects to a model."""
    fields = ("joint_batch", "window", "joint_learning_rate", "dynamics_weight", "heatmap_weight")
    fields += ("constraint_weight", "constraint_drift", "augment", "warmup_steps", "final_learning_rate")
    chosen = {name: recipe[name] for name in fields if recipe.get(name) is not None}
    return Schedule(autoencoder_steps=0, dynamics_steps=0, joint_steps=steps, refit_steps=0, **chosen)
