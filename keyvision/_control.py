"""Energy-shaping control from camera frames (paper section 4): a target image in, a swing-up out.

`image_target` turns a target frame into the target keypoints `x*`; `FramePolicy` turns camera frames
into controls (estimator -> keypoints -> velocity by finite differences projected onto the constraint
tangent space -> `cldyn.EnergyShaping` with the learnt potential and input matrix); `swing_up` closes
the loop with MuJoCo, the policy seeing only rendered frames.
"""

import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

import cldyn
from cldyn._control import hinge_extremes
from cldyn._misc import check_positive

from ._data import PlanarCamera
from ._evaluate import encode_batch
from ._model import KeyCLD, parameter_dtype
from ._render import RenderProtocol, _scene_xml
from ._scene import _HINGE, _Camera, _mujoco, _scene

_SETTLE = 0.5  # seconds at the end of a run over which the target must hold
_SHADOW_SIZE = 512


def _as_images(frames) -> Array:
    """uint8 `0..255` or float `[0, 1]` frames as float32 `[0, 1]`; any other dtype is refused (a
    uint16 frame taken for floats would be thousands of times too bright)."""
    frames = jnp.asarray(frames)
    if frames.dtype == jnp.uint8:
        return frames.astype(jnp.float32) / 255.0
    if not jnp.issubdtype(frames.dtype, jnp.floating):
        raise TypeError(f"frames must be uint8 0..255 or float in [0, 1], got dtype {frames.dtype}")
    return frames.astype(jnp.float32)


def image_target(model: KeyCLD, frame: Float[Array, "H W 3"]) -> Float[Array, " k"]:
    """The target keypoints `x*` of a target frame: what the model's estimator sees in it.

    **Arguments:**

    - `model`: a `keyvision.KeyCLD`.
    - `frame`: one image `(H, W, 3)`, uint8 `0..255` or float `[0, 1]`, of the model's size.

    **Returns:** `(2K,)` keypoints in the image frame, the `x*` of `cldyn.EnergyShaping`.
    """
    frame = _as_images(frame)
    if frame.shape != (model.image_size, model.image_size, 3):
        raise ValueError(
            f"image_target: the frame has shape {tuple(frame.shape)}; the model takes "
            f"({model.image_size}, {model.image_size}, 3)"
        )
    return model.encode(frame)


class FramePolicy(eqx.Module):
    """Energy shaping (eq. 32) driven by camera frames through a learnt KeyCLD model.

    Each call takes the newest frame and a memory of the last three estimated keypoint sets. The
    state is the newest keypoints `x_t` and the second-order backward difference
    `xd = (3 x_t - 4 x_{t-1} + x_{t-2}) / (2 dt)`, projected onto the tangent space of the learnt
    constraints at `x_t` (`xd - J^T (J J^T)^{-1} J xd`): differences of noisy keypoints leave the
    constraint manifold, and the constrained dynamics only know tangent velocities. A backward
    difference, not the central one of `keyvision.predict`, because the controller acts on the newest
    frame. The first frames of a run repeat the first keypoints (velocity zero).

    **Arguments:**

    - `model`: a trained `keyvision.KeyCLD` whose dynamics are a `cldyn.ConstrainedLagrangian`
      (KeyCLD, KeyCLD-NC) with a potential and an input matrix.
    - `target`: the target keypoints `(2K,)`, or a target frame `(H, W, 3)` (see `image_target`).
    - `dt`: the time between frames, in seconds (the control period).
    - `kp`, `kd`, `limit`, `damping`, `metric`, `trim`: as `cldyn.EnergyShaping` (the paper: `kp = 5`,
      `kd = 2`, `metric="euclidean"`, no trim). A Lagrangian learnt from images has an arbitrary scale, at
      which eq. 32's gains act: `metric="mass"` makes them rates that do not depend on it.

    !!! example

        ```python
        policy = keyvision.FramePolicy(model, target_frame, dt=0.02)
        memory = policy.start(first_frame)
        u, memory = policy(frame, memory)      # every frame
        ```
    """

    model: KeyCLD
    controller: cldyn.EnergyShaping
    dt: float = eqx.field(static=True)

    def __init__(
        self,
        model: KeyCLD,
        target,
        dt: float,
        *,
        kp: float = 5.0,
        kd: float = 2.0,
        limit: float | None = None,
        damping: str = "keypoint",
        metric: str = "euclidean",
        trim: bool = False,
    ):
        if not isinstance(model, KeyCLD):
            raise TypeError(f"FramePolicy: model must be a keyvision.KeyCLD, got {type(model).__name__}")
        if not isinstance(model.dynamics, cldyn.ConstrainedLagrangian):
            raise TypeError(
                "FramePolicy: energy shaping needs a learnt potential and input matrix, i.e. dynamics that "
                f"are a cldyn.ConstrainedLagrangian (KeyCLD, KeyCLD-NC), got {type(model.dynamics).__name__}"
            )
        if not dt > 0:
            raise ValueError(f"FramePolicy: dt must be positive, got {dt}")
        target = jnp.asarray(target)
        if target.ndim == 3:
            target = image_target(model, target)
        dtype = parameter_dtype(model.dynamics)
        self.model = model
        self.controller = cldyn.EnergyShaping(
            model.dynamics,
            target.astype(dtype),
            kp,
            kd,
            limit=limit,
            damping=damping,
            metric=metric,
            trim=trim,
        )
        self.dt = float(dt)

    @property
    def target(self) -> Float[Array, " k"]:
        """The target keypoints `x*`."""
        return self.controller.x_target

    def start(self, frame: Float[Array, "H W 3"]) -> Float[Array, "3 k"]:
        """The memory at the first frame of a run: its keypoints, three times."""
        x = self.model.encode(_as_images(frame))
        return jnp.stack([x, x, x])

    def state(self, memory: Float[Array, "3 k"]) -> tuple[Float[Array, " k"], Float[Array, " k"]]:
        """`(x, xd)` from the memory: the newest keypoints and the projected backward difference."""
        memory = jnp.asarray(memory, self.target.dtype)
        x = memory[-1]
        xd = (3.0 * memory[-1] - 4.0 * memory[-2] + memory[-3]) / (2.0 * self.dt)
        system = self.model.dynamics
        if system.num_constraints:
            jac = system.constraint.jacobian(x)
            xd = xd - jac.T @ jnp.linalg.solve(jac @ jac.T, jac @ xd)
        return x, xd

    def __call__(
        self, frame: Float[Array, "H W 3"], memory: Float[Array, "3 k"]
    ) -> tuple[Float[Array, " l"], Float[Array, "3 k"]]:
        """The control for the newest `frame`, and the memory for the next call."""
        x = self.model.encode(_as_images(frame))
        memory = jnp.concatenate([memory[1:], x[None]])
        return self.controller(0.0, *self.state(memory)), memory


@eqx.filter_jit
def _frame_step(policy: FramePolicy, frame, memory):
    """One control period, compiled: the control, the new memory and the state the policy used."""
    u, memory = policy(frame, memory)
    return u, memory, *policy.state(memory)


@eqx.filter_jit
def _frame_start(policy: FramePolicy, frame):
    return policy.start(frame)


@eqx.filter_jit
def _state_step(policy: FramePolicy, x, xd):
    return policy.controller(0.0, x, xd)


@eqx.filter_jit
def _energy(policy: FramePolicy, x, xd):
    return jax.vmap(policy.model.dynamics.energy)(x, xd)


def _postures(mujoco, scene, data, camera: PlanarCamera) -> tuple[np.ndarray, np.ndarray]:
    """`(hanging, upright)` joint positions: each hinge at 0 or pi, whichever puts the keypoints
    lowest or highest in the image (slides at their reference position)."""
    model = scene.model
    hinges = [j for j in range(model.njnt) if model.jnt_type[j] == _HINGE]

    def posture(angles):
        qpos = np.array(model.qpos0)
        for j, angle in zip(hinges, angles):
            qpos[model.jnt_qposadr[j]] = angle
        return qpos

    def height(angles):
        data.qpos[:] = posture(angles)
        mujoco.mj_forward(model, data)
        return float(np.sum(camera.to_image(_true_keypoints(scene, data))[:, 1]))

    low, high = hinge_extremes(len(hinges), height)
    return posture(low), posture(high)


def _true_keypoints(scene, data) -> np.ndarray:
    """The scene's keypoints in plane coordinates (metres), `(K, 2)`."""
    return np.stack([scene.basis @ point.world(data) for point in scene.keypoints])


def _model_scene(model: KeyCLD, scene, camera, caller: str, supersample: int = 1):
    """`(protocol, scene)`: the render protocol at the model's image size and the scene seen by
    `camera`, refused if its keypoints are not the model's in number."""
    # a 512-texel shadow map renders the same pixels at 64 x 64 as the scenes' 2048 (a test checks)
    # in half the time
    protocol = RenderProtocol(image_size=model.image_size, shadow_size=_SHADOW_SIZE, supersample=supersample)
    setup = _scene(_scene_xml(scene), protocol, camera, None)
    if len(setup.keypoints) != model.num_keypoints:
        raise ValueError(
            f"{caller}: {scene} has {len(setup.keypoints)} keypoints, the model {model.num_keypoints}"
        )
    return protocol, setup


def swing_up(
    model: KeyCLD,
    scene: "str | os.PathLike" = "keycld/pendulum",
    *,
    observe: str = "frames",
    target=None,
    kp: float = 5.0,
    kd: float = 2.0,
    limit: float | None = None,
    metric: str = "euclidean",
    trim: bool = False,
    runs: int = 20,
    duration: float = 10.0,
    tolerance: float = 0.05,
    perturbation: float = 0.2,
    seed: int = 0,
    dt: float | None = None,
    physics_dt: float = 0.002,
    camera: str | int = "fixed",
    supersample: int = 1,
    keep_frames: int = 1,
    progress_meter: cldyn.AbstractProgressMeter = cldyn.NoProgressMeter(),
) -> dict:
    """Swing a MuJoCo scene up with energy shaping on a model learnt from images, seeing only frames.

    Each run starts near the hanging posture (hinge angles within `perturbation` rad of it,
    velocities within 0.1). At every control period MuJoCo's state is rendered by the camera the model
    was trained with, and the `FramePolicy` turns the frame into a control, held while MuJoCo steps
    (RK4 at `physics_dt`). MuJoCo's state serves only the renderer and the scoring: a run succeeds when
    every true keypoint is within `tolerance` metres of its place in the upright posture over the last
    0.5 s. With `observe="state"` the policy gets the true keypoints and velocities instead of the
    frames' estimate, mapped into the model's keypoint frame by an affine fit of the estimated keypoints
    to the true ones on 200 rendered poses (a learnt keypoint need not sit where the scene's does), and
    the default target is the upright posture through the same map (not the estimator's reading of the
    target frame, which differs from it by the fit's residual there, about a pixel on the acrobot): what
    seeing through the camera costs.

    **Arguments:**

    - `model`: a trained `keyvision.KeyCLD` of `scene`.
    - `scene`: what `keyvision.render` accepts (`"keycld/pendulum"`, an MJCF, ...).
    - `observe`: `"frames"` (the policy sees rendered frames) or `"state"` (true state, for reference).
    - `target`: a target frame `(H, W, 3)`; by default the scene rendered in its upright posture
      (with `observe="state"`, a given frame is read by the estimator, the default is calibrated).
    - `kp`, `kd`, `limit`, `metric`, `trim`: the controller's gains, saturation, metric and trim
      (`cldyn.EnergyShaping`; `metric="mass"` for gains that do not depend on the learnt Lagrangian's
      arbitrary scale; `trim=True` subtracts the learnt command at the target, not part of eq. 32).
    - `runs`, `duration`, `tolerance`, `perturbation`, `seed`: the protocol.
    - `dt`: the control period; by default the frame interval of `keyvision.render`'s protocol for
      the scene (its timestep: 0.02 s for the pendulum, 0.01 s for the cart-pole and the acrobot).
    - `physics_dt`: MuJoCo's step; must divide `dt`.
    - `camera`, `supersample`: the camera the model was trained with, and the samples per pixel along
      each side of its frames (`keyvision.RenderProtocol`; 1, MuJoCo's render, for the paper's frames).
    - `keep_frames`: how many runs keep their frames and estimated keypoints in the result (for GIFs).
    - `progress_meter`: reports the runs.

    **Returns:** a dict: `success_rate`, per-run `success`, `final_error` and `time_to_tolerance`
    (seconds, `None` if never), `ts`, `errors` `(runs, T)` (metres), `qpos` `(runs, T, nq)`, `u`
    `(runs, T, l)`, `x`/`xd` (the policy's state, image frame), `energy` (the learnt energy along it),
    `target_keypoints` (image frame), `frames` and `target_frame`, and the loop's timing: `seconds`
    per control step for rendering and for the policy, and `steps_per_second` against the real-time
    rate `1 / dt`.
    """
    if observe not in ("frames", "state"):
        raise ValueError(f"swing_up: observe must be 'frames' or 'state', got {observe!r}")
    check_positive("runs", runs, integer=True)
    for name, value in (("duration", duration), ("tolerance", tolerance), ("physics_dt", physics_dt)):
        check_positive(name, value)
    mujoco = _mujoco()
    protocol, setup = _model_scene(model, scene, camera, "swing_up", supersample)
    frame_dt = float(setup.model.opt.timestep) * protocol.steps_per_frame if dt is None else float(dt)
    substeps = int(round(frame_dt / physics_dt))
    if substeps < 1 or abs(substeps * physics_dt - frame_dt) > 1e-9 * frame_dt:
        raise ValueError(f"swing_up: physics_dt {physics_dt} must divide the control period {frame_dt}")
    view = PlanarCamera(setup.homography, setup.basis)
    renderer = _Camera(mujoco, setup, protocol)
    try:
        data = mujoco.MjData(setup.model)
        hanging, upright = _postures(mujoco, setup, data, view)
        data.qpos[:] = upright
        data.qvel[:] = 0.0
        mujoco.mj_forward(setup.model, data)
        target_world = _true_keypoints(setup, data)
        target_frame = renderer.render(data) if target is None else np.asarray(target)
        rng = np.random.default_rng(seed)
        calibration, target_keypoints = None, target_frame
        if observe == "state":
            calibration = _calibrate(mujoco, setup, data, renderer, model, view, rng)
            if target is None:
                # the upright posture through the same map as the state: the estimator's own reading
                # of the target frame differs from it by the calibration's residual there
                target_keypoints = _calibrated(calibration, view.to_image(target_world))
        policy = FramePolicy(
            model, target_keypoints, frame_dt, kp=kp, kd=kd, limit=limit, metric=metric, trim=trim
        )
        physics = setup.model
        physics.opt.timestep = physics_dt
        physics.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
        qpos0 = np.tile(hanging, (runs, 1))
        hinge_dofs = [physics.jnt_qposadr[j] for j in range(physics.njnt) if physics.jnt_type[j] == _HINGE]
        qpos0[:, hinge_dofs] += rng.uniform(-perturbation, perturbation, size=(runs, len(hinge_dofs)))
        qvel0 = rng.uniform(-0.1, 0.1, size=(runs, physics.nv))
        samples = int(round(duration / frame_dt)) + 1
        k, nu = 2 * model.num_keypoints, physics.nu
        out = {
            "qpos": np.zeros((runs, samples, physics.nq)),
            "keypoints": np.zeros((runs, samples, model.num_keypoints, 2)),
            "u": np.zeros((runs, samples, nu)),
            "x": np.zeros((runs, samples, k)),
            "xd": np.zeros((runs, samples, k)),
        }
        kept = []
        render_seconds = policy_seconds = 0.0
        # compile before the clock runs (at the target: a state where the constraints are regular)
        warm = jnp.asarray(target_frame)
        jax.block_until_ready(_frame_step(policy, warm, _frame_start(policy, warm)))
        jax.block_until_ready(_state_step(policy, policy.target, jnp.zeros(k, policy.target.dtype)))
        meter = progress_meter.start(runs, desc="swing-up", unit="run")
        for r in range(runs):
            mujoco.mj_resetData(physics, data)
            data.qpos[:] = qpos0[r]
            data.qvel[:] = qvel0[r]
            memory, frames = None, []
            for s in range(samples):
                mujoco.mj_forward(physics, data)
                true = _true_keypoints(setup, data)
                out["qpos"][r, s] = data.qpos
                out["keypoints"][r, s] = true
                started = time.perf_counter()
                if observe == "frames":
                    frame = renderer.render(data)
                    render_seconds += time.perf_counter() - started
                    started = time.perf_counter()
                    if memory is None:
                        memory = _frame_start(policy, frame)
                    u, memory, x, xd = _frame_step(policy, frame, memory)
                    u, x, xd = np.asarray(u), np.asarray(x), np.asarray(xd)
                    if r < keep_frames:
                        frames.append(frame)
                else:
                    x, xd = _model_state(mujoco, setup, data, view, calibration)
                    dtype = policy.target.dtype
                    u = np.asarray(_state_step(policy, jnp.asarray(x, dtype), jnp.asarray(xd, dtype)))
                policy_seconds += time.perf_counter() - started
                out["u"][r, s], out["x"][r, s], out["xd"][r, s] = u, x, xd
                data.ctrl[:] = u
                for _ in range(substeps):
                    mujoco.mj_step(physics, data)
            if frames:
                kept.append(np.stack(frames))
            meter = progress_meter.update(meter, r + 1)
        progress_meter.close(meter)
    finally:
        renderer.close()
    errors = np.linalg.norm(out["keypoints"] - target_world[None, None], axis=-1).max(axis=-1)
    window = max(1, int(round(_SETTLE / frame_dt)))
    success = errors[:, -window:].max(axis=1) < tolerance
    ts = frame_dt * np.arange(samples)
    reached = [float(ts[np.argmax(e < tolerance)]) if (e < tolerance).any() else None for e in errors]
    steps = runs * samples
    per_step = (render_seconds + policy_seconds) / steps
    energy = np.asarray(
        _energy(
            policy,
            jnp.asarray(out["x"].reshape(-1, k), policy.target.dtype),
            jnp.asarray(out["xd"].reshape(-1, k), policy.target.dtype),
        )
    ).reshape(runs, samples)
    return {
        "scene": str(scene),
        "observe": observe,
        "kp": kp,
        "kd": kd,
        "metric": metric,
        "trim": trim,
        "runs": runs,
        "duration": duration,
        "dt": frame_dt,
        "tolerance": tolerance,
        "success_rate": float(success.mean()),
        "success": success.tolist(),
        "final_error": errors[:, -1].tolist(),
        "time_to_tolerance": reached,
        "ts": ts,
        "errors": errors,
        "qpos": out["qpos"],
        "u": out["u"],
        "x": out["x"],
        "xd": out["xd"],
        "energy": energy,
        "target_keypoints": np.asarray(policy.target),
        "target_true_keypoints": view.to_image(target_world).reshape(-1),
        "target_frame": np.asarray(target_frame),
        "frames": kept,
        "seconds": {
            "render_per_step": render_seconds / steps,
            "policy_per_step": policy_seconds / steps,
        },
        "steps_per_second": 1.0 / per_step,
        "real_time_rate": 1.0 / frame_dt,
    }


def _model_state(mujoco, scene, data, view, calibration) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's true state (`data`, after `mj_forward`) as the model's `(x, xd)`: the keypoints'
    positions through the camera, their velocities through its local linearisation (a central
    difference of the map), then into the model's keypoint frame by the affine `calibration`."""
    true = _true_keypoints(scene, data)
    velocity = np.stack(
        [scene.basis @ _point_velocity(mujoco, scene.model, data, point) for point in scene.keypoints]
    )
    h = 1e-6
    xd = (view.to_image(true + h * velocity) - view.to_image(true - h * velocity)) / (2 * h)
    # the learnt keypoint need not sit on the true one
    return _calibrated(calibration, view.to_image(true)), calibration[0] @ xd.reshape(-1)


def _calibrated(calibration, keypoints) -> np.ndarray:
    """True keypoints `(K, 2)` in the image frame -> the model's keypoint frame `(2K,)`."""
    return calibration[0] @ np.asarray(keypoints).reshape(-1) + calibration[1]


def _calibrate(mujoco, scene, data, renderer, model, view, rng, poses: int = 200):
    """`(A, b)` with `A x_true + b` the affine map from the true keypoints (image frame) to the
    model's estimated ones, least squares over frames of random poses: the learnt keypoints are the
    estimator's, which may sit elsewhere on the body than the scene's (on the pendulum, partway along
    the rod), and the state variant of `swing_up` must speak the model's coordinates."""
    truths, frames = _pose_frames(mujoco, scene, data, renderer, view, rng, poses)
    estimated = np.asarray(encode_batch(model, frames))
    design = np.concatenate([truths, np.ones((poses, 1))], axis=1)
    solution, *_ = np.linalg.lstsq(design, estimated, rcond=None)
    return solution[:-1].T, solution[-1]


def _pose_frames(mujoco, scene, data, renderer, view, rng, poses: int) -> tuple[np.ndarray, np.ndarray]:
    """`(truths, frames)` of `poses` random poses (hinges uniform on the circle, slides within 1 of
    their reference): the true keypoints in the image frame `(poses, 2K)` and the rendered frames."""
    physics = scene.model
    truths, frames = [], []
    for _ in range(poses):
        for j in range(physics.njnt):
            adr = physics.jnt_qposadr[j]
            if physics.jnt_type[j] == _HINGE:
                data.qpos[adr] = rng.uniform(-np.pi, np.pi)
            else:
                data.qpos[adr] = physics.qpos0[adr] + rng.uniform(-1.0, 1.0)
        mujoco.mj_forward(physics, data)
        truths.append(view.to_image(_true_keypoints(scene, data)).reshape(-1))
        frames.append(renderer.render(data))
    return np.stack(truths), np.stack(frames)


def _point_velocity(mujoco, model, data, point) -> np.ndarray:
    """World velocity of a point fixed in a body: MuJoCo's translational Jacobian there times `qvel`."""
    jacp = np.zeros((3, model.nv))
    mujoco.mj_jac(model, data, jacp, None, point.world(data), point.body)
    return jacp @ data.qvel
