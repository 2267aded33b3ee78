"""`target_linearisation`: the true closed loop of `swing_up` linearised at the upright target, with the
controller fed the true state or what the camera reads.

Whether energy shaping on a learnt model can hold the target at all is a property of MuJoCo's dynamics
under the learnt controller near the target; a swing-up answers it only after seconds of simulated
runs, this in a few dozen evaluations of MuJoCo's accelerations.
"""

import os

import jax.numpy as jnp
import numpy as np

from cldyn._misc import check_positive

from ._control import (
    FramePolicy,
    _as_images,
    _calibrate,
    _calibrated,
    _model_scene,
    _model_state,
    _postures,
    _state_step,
    _true_keypoints,
)
from ._data import PlanarCamera
from ._model import KeyCLD
from ._scene import _Camera, _mujoco

_REST_ITERATIONS = 8  # chord steps from the linearised rest
_OFFSETS = np.linspace(-1.0, 1.0, 5)  # the frames' pose offsets, in units of `amplitude`


def _slope(offsets: np.ndarray, values: list) -> np.ndarray:
    """The least-squares slope of `values` (one array per offset) against `offsets` (centred)."""
    values = np.stack(values)
    centred = offsets - offsets.mean()
    return np.tensordot(centred, values - values.mean(axis=0), axes=1) / np.dot(centred, centred)


def target_linearisation(
    model: KeyCLD,
    scene: "str | os.PathLike" = "keycld/pendulum",
    *,
    observe: str = "state",
    kp: float = 5.0,
    kd: float = 2.0,
    metric: str = "euclidean",
    trim: bool = False,
    camera: str | int = "fixed",
    supersample: int = 1,
    step: float = 1e-4,
    amplitude: float = 0.05,
    seed: int = 0,
) -> dict:
    """The true closed loop at the upright target: MuJoCo's dynamics under the learnt controller,
    linearised there. Says whether energy shaping on `model` can hold the target at all, from the
    true state or through the camera.

    With `observe="state"` the controller is `swing_up`'s with `observe="state"` (true keypoints and
    velocities mapped into the model's keypoint frame by the same affine calibration, the target the
    calibrated upright posture). MuJoCo's joint accelerations under that control are differenced
    centrally (`step` in joint units) in positions and velocities about the upright posture at rest,
    giving the closed loop's matrix `[[0, I], [dqacc/dq, dqacc/dqvel]]`; an eigenvalue with a positive
    real part means the target is unstable in truth, whatever the learnt model predicts.

    With `observe="frames"` the controller is `swing_up`'s from frames: it reads the keypoints from the
    scene rendered in each posture, aims at its reading of the upright frame, and takes velocities as
    the camera's reading of a steady motion, `J qd` projected as `keyvision.FramePolicy` projects its
    backward difference (`J` the reading's slope at the target). The camera resolves a posture in
    steps of a fraction of a pixel, so a difference over `step` reads nothing or a step: the slopes in
    the positions (of the reading and of the accelerations) are least squares over postures turned
    from upright by up to `amplitude` (joint units) each way, five per joint. The result is the loop
    for excursions of that size, and the part of the camera's error that varies over them (its warp
    near the target) enters it, which the state's calibration averages out over all poses. The
    backward difference's delay (a frame) is left out.

    Beside it, the scene's own gravity rates at the target: the eigenvalues of `M^-1 G` (`G` the
    destabilising stiffness of gravity, `-d qfrc_bias / dq`, `M` the joint mass matrix). With
    `metric="mass"` and exact masses, the shaped spring holds a learnt potential whose curvature
    along a mode is wrong by less than `kp / rate` of the truth: the fastest rate sets how exact a
    learnt potential must be.

    **Arguments:** `model`, `scene`, `kp`, `kd`, `metric`, `trim`, `camera` and `supersample` as
    `swing_up`; `observe`: `"state"` or `"frames"`; `step`: the finite-difference step (velocities,
    and positions from the state); `amplitude`: the largest turn of a joint from upright over which
    the frames' slopes are taken; `seed`: the calibration's random poses.

    **Returns:** a dict: `observe`, `eigenvalues` (of the true closed loop, complex, as `[real, imag]`
    pairs sorted by real part, largest first), `largest_real_part` (1/s; positive: unstable),
    `gravity_rates` (1/s², the eigenvalues of `M^-1 G`, largest first), `curvature_tolerance` (`kp` over
    the largest rate), `control_at_target` (the learnt controller's command at rest at the true upright
    posture; zero for an exact model), `rest_offset` (joint units: where the true loop comes to rest, off
    upright: first `-S^-1 a`, with `S` the stiffness block and `a` the joint accelerations that the
    command at target causes, then chord steps with the same `S` on MuJoCo's accelerations at rest, the
    posture of the smallest accelerations among them; meaningful where the loop is stable), `rest_error`
    (metres: the largest distance of a true keypoint from its upright place in that posture, what
    `swing_up`'s tolerance measures) and `rest_residual` (the norm of MuJoCo's joint accelerations at
    upright and at that rest: from the state it falls to about zero where the chord steps converge;
    through the camera less, as the reading changes in steps and no posture balances the loop exactly);
    with `observe="frames"` also `camera_gain`, per joint the share of a turn of that joint near upright
    that the camera's reading follows (the reading's slope projected on the calibrated true keypoints'
    motion; 1 for an estimator that follows the pose as the calibration maps it) and `amplitude`.

    Near upright the loop balances `kp M (q - q*) = G (q_V - q_up)` for a learnt potential of the right
    curvature whose own upright is `q_V` (`q_up` the true one): an error of the learnt upright comes back
    multiplied by the gravity rate over `kp` (about 9 along the acrobot's fast mode).
    """
    if observe not in ("state", "frames"):
        raise ValueError(f"target_linearisation: observe must be 'state' or 'frames', got {observe!r}")
    check_positive("target_linearisation: step", step)
    check_positive("target_linearisation: amplitude", amplitude)
    mujoco = _mujoco()
    protocol, setup = _model_scene(model, scene, camera, "target_linearisation", supersample)
    physics = setup.model
    if physics.nq != physics.nv:
        raise ValueError("target_linearisation: needs a scene of hinges and slides (nq == nv)")
    view = PlanarCamera(setup.homography, setup.basis)
    renderer = _Camera(mujoco, setup, protocol)
    n = physics.nv
    rest = np.zeros(n)
    try:
        data = mujoco.MjData(physics)
        _, upright = _postures(mujoco, setup, data, view)

        def posed(qpos):
            """`data` at rest at `qpos`, forwarded."""
            data.qpos[:], data.qvel[:] = qpos, 0.0
            mujoco.mj_forward(physics, data)
            return data

        def reading(qpos) -> np.ndarray:
            """The estimator's keypoints from the scene rendered at `qpos`, at rest."""
            return np.asarray(model.encode(_as_images(renderer.render(posed(qpos)))))

        def seen(qpos) -> np.ndarray:
            """The true keypoints at `qpos` in the image frame, `(2K,)`."""
            return view.to_image(_true_keypoints(setup, posed(qpos))).reshape(-1)

        upright_world = _true_keypoints(setup, posed(upright))
        frame_dt = float(physics.opt.timestep) * protocol.steps_per_frame
        calibration = _calibrate(mujoco, setup, data, renderer, model, view, np.random.default_rng(seed))
        if observe == "state":
            target = _calibrated(calibration, view.to_image(upright_world))
        else:
            target = reading(upright)
            offsets = amplitude * _OFFSETS
            turned = [[upright + a * np.eye(n)[j] for a in offsets] for j in range(n)]
            readings = [[reading(q) for q in postures] for postures in turned]
            slope = np.stack([_slope(offsets, row) for row in readings], axis=1)
            # the true keypoints' motion per joint, into the model's keypoint frame by the calibration
            truth = calibration[0] @ np.stack(
                [(seen(upright + e) - seen(upright - e)) / (2 * step) for e in step * np.eye(n)], axis=1
            )
            gain = np.einsum("kj,kj->j", slope, truth) / np.einsum("kj,kj->j", truth, truth)
        policy = FramePolicy(model, target, frame_dt, kp=kp, kd=kd, metric=metric, trim=trim)
        dtype = policy.target.dtype

        def controlled_state(qpos, qvel, x=None):
            """`(x, xd)` as the controller gets them at `(qpos, qvel)` (`x`: a reading already made)."""
            if observe == "state":
                data.qpos[:], data.qvel[:] = qpos, qvel
                mujoco.mj_forward(physics, data)
                x, xd = _model_state(mujoco, setup, data, view, calibration)
                return jnp.asarray(x, dtype), jnp.asarray(xd, dtype)
            x = reading(qpos) if x is None else x
            velocity = slope @ qvel  # a steady motion read by the camera, differenced as the policy does
            memory = np.stack([x - 2 * frame_dt * velocity, x - frame_dt * velocity, x])
            return policy.state(jnp.asarray(memory, dtype))

        def acceleration(qpos, qvel, control: bool = True, x=None):
            command = np.zeros(physics.nu)
            if control:
                command = np.asarray(_state_step(policy, *controlled_state(qpos, qvel, x)))
            data.qpos[:], data.qvel[:] = qpos, qvel
            data.ctrl[:] = command
            mujoco.mj_forward(physics, data)
            return data.qacc.copy(), data.ctrl.copy()

        stiffness, damping, gravity = (np.zeros((n, n)) for _ in range(3))
        for j, e in enumerate(step * np.eye(n)):
            if observe == "state":
                ahead, behind = acceleration(upright + e, rest)[0], acceleration(upright - e, rest)[0]
                stiffness[:, j] = (ahead - behind) / (2 * step)
            else:
                accelerations = [acceleration(q, rest, x=x)[0] for q, x in zip(turned[j], readings[j])]
                stiffness[:, j] = _slope(offsets, accelerations)
            x_up = None if observe == "state" else target  # the reading at upright is the target
            ahead, behind = acceleration(upright, e, x=x_up)[0], acceleration(upright, -e, x=x_up)[0]
            damping[:, j] = (ahead - behind) / (2 * step)
            gravity[:, j] = (
                acceleration(upright + e, rest, False)[0] - acceleration(upright - e, rest, False)[0]
            ) / (2 * step)
        closed = np.block([[np.zeros((n, n)), np.eye(n)], [stiffness, damping]])
        eigenvalues = sorted(np.linalg.eigvals(closed), key=lambda z: -z.real)
        # M^-1 G is d qacc / d qpos without control at rest: gravity's rates
        rates = np.sort(np.linalg.eigvals(gravity).real)[::-1]
        at_target, command = acceleration(upright, rest)
        # the loop's rest, qacc(upright + offset, 0) = 0: linearised, then chord steps with the same S;
        # the most balanced of the postures they visit (through the camera, where the reading changes in
        # steps, the steps need not settle)
        offset, residual = np.zeros(n), at_target
        best = (np.linalg.norm(residual), offset)
        for _ in range(_REST_ITERATIONS):
            offset = offset - np.linalg.lstsq(stiffness, residual, rcond=None)[0]
            residual = acceleration(upright + offset, rest)[0]
            best = min(best, (np.linalg.norm(residual), offset), key=lambda b: b[0])
        balance, offset = best
        data.qpos[:], data.qvel[:] = upright + offset, rest
        mujoco.mj_forward(physics, data)
        rest_error = np.linalg.norm(_true_keypoints(setup, data) - upright_world, axis=-1).max()
    finally:
        renderer.close()
    result = {
        "observe": observe,
        "eigenvalues": [[float(z.real), float(z.imag)] for z in eigenvalues],
        "largest_real_part": float(eigenvalues[0].real),
        "gravity_rates": rates.tolist(),
        "curvature_tolerance": float(kp / rates[0]) if rates[0] > 0 else float("inf"),
        "control_at_target": command.tolist(),
        "rest_offset": offset.tolist(),
        "rest_error": float(rest_error),
        "rest_residual": [float(np.linalg.norm(at_target)), float(balance)],
    }
    if observe == "frames":
        result.update(camera_gain=gain.tolist(), amplitude=float(amplitude))
    return result
