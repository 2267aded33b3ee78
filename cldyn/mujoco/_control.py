"""Keypoint feedback control of MuJoCo scenes: `closed_loop` and the energy-shaping `swing_up`."""

import os
from collections.abc import Callable, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._control import EnergyShaping, hinge_extremes
from .._data import Sequences
from .._misc import atomic_save, check_positive, optional_import
from .._progress import AbstractProgressMeter, NoProgressMeter
from .._system import ConstrainedLagrangian
from ._bridge import MujocoModel, from_mjcf
from ._record import record
from ._scenes import load_model
from ._tree import _HINGE


@eqx.filter_jit
def _policy(joints, controller, shift, t, qpos, qvel):
    # One compiled program per scene structure and controller type: the bridge's joint maps and the
    # controller are arguments (their arrays traced), not constants of a closure.
    x, xd = joints.to_keypoints(qpos, qvel)
    return controller(t, x - jnp.tile(shift, x.shape[0] // shift.shape[0]), xd)


def closed_loop(
    mjcf: "str | os.PathLike",
    controller: Callable,
    *,
    runs: int,
    duration: float,
    initial,
    dt: float = 0.01,
    physics_dt: float = 0.002,
    origin: Sequence[float] | None = None,
    keypoints: Sequence[str] | None = None,
    seed: int = 0,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> Sequences:
    """Run a keypoint feedback policy on a MuJoCo scene.

    At every sample MuJoCo's state is read as keypoints (positions and velocities of the scene's
    keypoints, through `from_mjcf`'s exact map), the policy `u = controller(t, x, xd)` is evaluated
    (jit-compiled) and held until the next sample while MuJoCo steps with RK4.

    **Arguments:**

    - `mjcf`: the scene (path, XML string, suite name or `"keycld/<name>"`).
    - `controller`: a policy `u(t, x, xd)` in keypoint coordinates, e.g. `cldyn.EnergyShaping`.
    - `runs`, `duration`: number of runs and seconds per run.
    - `initial`: `(qpos, qvel)` arrays of shape `(runs, nq)` and `(runs, nv)`.
    - `dt`, `physics_dt`: control period and MuJoCo's step.
    - `origin`: a point `(2,)` subtracted from every keypoint before the policy sees it (models
      learned on `keycld_dataset`, whose keypoints are relative to the scene's pivot).
    - `keypoints`: site names, if not the scene's default keypoints.
    - `seed`, `progress_meter`: as in `record`.

    **Returns:** the `cldyn.Sequences` of the closed-loop runs, as `record` returns them.
    """
    bridge = from_mjcf(mjcf, keypoints=keypoints)
    shift = jnp.zeros(2) if origin is None else jnp.asarray(origin, dtype=float)

    def control(t, qpos, qvel):
        t, qpos, qvel = jnp.asarray(t, dtype=float), jnp.asarray(qpos), jnp.asarray(qvel)
        return np.asarray(_policy(bridge.joints, controller, shift, t, qpos, qvel))

    return record(
        mjcf,
        runs=runs,
        duration=duration,
        dt=dt,
        physics_dt=physics_dt,
        integrator="rk4",
        initial=initial,
        control=control,
        keypoints=keypoints,
        seed=seed,
        progress_meter=progress_meter,
    )


def _postures(bridge: MujocoModel, hinge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(hanging, upright)` joint positions: every hinge at the angle that puts the keypoints lowest or
    highest (slides at zero). `hinge` marks the hinges among the joints."""
    hinges = [int(j) for j in np.flatnonzero(hinge)]

    def posture(angles):
        q = np.zeros(len(bridge.joint_names))
        q[hinges] = angles
        return q

    def height(angles):
        keypoints = np.asarray(bridge.joints.keypoints(jnp.asarray(posture(angles))))
        return float(np.sum(keypoints.reshape(-1, 2)[:, 1]))

    low, high = hinge_extremes(len(hinges), height)
    return posture(low), posture(high)


def swing_up(
    mjcf: "str | os.PathLike",
    *,
    kp: float = 5.0,
    kd: float = 2.0,
    damping: str = "keypoint",
    system=None,
    origin: Sequence[float] | None = None,
    runs: int = 20,
    duration: float = 10.0,
    tolerance: float = 0.05,
    perturbation: float = 0.2,
    seed: int = 0,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> dict:
    """Energy-shaping swing-up (eq. 32) of a fully actuated MuJoCo scene, from hanging to upright.

    Each run starts near the hanging posture (joint angles within `perturbation` rad of it, velocities
    within 0.1) and is controlled by `EnergyShaping(system, x_upright, kp, kd)` built on `system` (the
    analytic `from_mjcf` model by default, or a learned one). A run succeeds when every keypoint is within
    `tolerance` of the upright target over the last 0.5 s before `duration`.

    **Arguments:**

    - `mjcf`: the scene.
    - `kp`, `kd`, `damping`: the controller's gains and damping form (see `EnergyShaping`).
    - `system`: the model the controller uses; `from_mjcf(mjcf).system` by default.
    - `origin`: subtracted from the keypoints the model sees (see `closed_loop`).
    - `runs`, `duration`, `tolerance`, `perturbation`, `seed`: the protocol.
    - `progress_meter`: reports MuJoCo's runs (e.g. `cldyn.TqdmProgressMeter()`).

    **Returns:** a dict with the success rate, per-run final errors and times to reach the tolerance,
    the error curves (`ts`, `errors` of shape `(runs, T)`) and the recording.
    """
    check_positive("runs", runs, integer=True)
    for name, value in (("duration", duration), ("tolerance", tolerance), ("kp", kp)):
        check_positive(name, value)
    check_positive("kd", kd, allow_zero=True)
    check_positive("perturbation", perturbation, allow_zero=True)
    bridge = from_mjcf(mjcf)
    if bridge.system.num_inputs < len(bridge.joint_names):
        raise ValueError(
            f"swing_up needs a fully actuated scene: {mjcf} has {len(bridge.joint_names)} joints "
            f"{list(bridge.joint_names)} but {bridge.system.num_inputs} actuators "
            f"{list(bridge.actuator_names)} (the keycld/ scenes are fully actuated)"
        )
    hanging, upright = _postures(bridge, load_model(mjcf)[0].jnt_type == _HINGE)
    shift = np.zeros(2) if origin is None else np.asarray(origin, dtype=float)
    target_world = np.asarray(bridge.joints.keypoints(jnp.asarray(upright)))
    model = bridge.system if system is None else system
    if not isinstance(model, ConstrainedLagrangian):  # energy shaping needs a mass matrix and a potential
        raise ValueError(
            f"swing_up needs a ConstrainedLagrangian (KeyCLD, KeyCLD-NC) for energy shaping, got "
            f"{type(model).__name__}"
        )
    if (model.size, model.num_inputs) != (bridge.system.size, bridge.system.num_inputs):
        raise ValueError(
            f"the system has {model.size} coordinates and {model.num_inputs} inputs, but {mjcf}'s keypoints "
            f"{list(bridge.keypoint_names)} give {bridge.system.size} and its actuators "
            f"{bridge.system.num_inputs}"
        )
    target = jnp.asarray(target_world - np.tile(shift, len(bridge.keypoint_names)), dtype=float)
    controller = EnergyShaping(model, target.astype(model.mass.matrix().dtype), kp, kd, damping=damping)
    rng = np.random.default_rng(seed)
    qpos = hanging + rng.uniform(-perturbation, perturbation, size=(runs, hanging.size))
    qvel = rng.uniform(-0.1, 0.1, size=qpos.shape)
    data = closed_loop(
        mjcf,
        controller,
        runs=runs,
        duration=duration,
        initial=(qpos, qvel),
        origin=origin,
        seed=seed,
        progress_meter=progress_meter,
    )
    x = np.asarray(data.extras["x_clean"]).reshape(runs, data.num_samples, -1, 2)
    errors = np.linalg.norm(x - target_world.reshape(1, 1, -1, 2), axis=-1).max(axis=-1)
    window = max(1, int(round(0.5 / data.dt)))
    success = errors[:, -window:].max(axis=1) < tolerance
    ts = np.asarray(data.ts)
    reached = [float(ts[np.argmax(e < tolerance)]) if (e < tolerance).any() else None for e in errors]
    return {
        "scene": str(mjcf),
        "kp": kp,
        "kd": kd,
        "damping": damping,
        "runs": runs,
        "duration": duration,
        "tolerance": tolerance,
        "success_rate": float(success.mean()),
        "success": success.tolist(),
        "final_error": errors[:, -1].tolist(),
        "time_to_tolerance": reached,
        "max_abs_control": float(np.abs(data.u).max()),
        "ts": ts,
        "errors": errors,
        "recording": data,
    }


def plot_swing_up(results: Sequence[dict], path: "str | os.PathLike") -> None:
    """Keypoint error to the upright target over time, one panel per result of `swing_up`.

    Needs matplotlib (the `[vision]` extra); the file is written atomically.
    """
    figure_module = optional_import("matplotlib.figure", purpose="plot_swing_up")
    figure = figure_module.Figure(figsize=(4.2 * len(results), 3.4))
    axes = figure.subplots(1, len(results), squeeze=False)
    for ax, result in zip(axes[0], results):
        for e in result["errors"]:
            ax.plot(result["ts"], e, lw=0.8, alpha=0.6)
        ax.axhline(result["tolerance"], color="k", ls="--", lw=1)
        ax.set_yscale("log")
        ax.set_title(
            f"{result['scene']} ({result['damping']}): {100 * result['success_rate']:.0f}% succeed",
            fontsize=9,
        )
        ax.set_xlabel("time (s)")
        ax.set_ylabel("max keypoint error to upright (m)")
    figure.tight_layout()
    atomic_save(path, lambda temporary: figure.savefig(temporary, dpi=120))
