"""`record`: trajectories of a MuJoCo scene, in joint and keypoint coordinates, with MuJoCo's forces.

MuJoCo itself computes everything recorded: keypoint velocities from the point Jacobians
(`mj_jac`), accelerations from `J qacc + Jdot qvel` (`mj_jacDot`).
"""

import os
from collections.abc import Callable, Sequence

import mujoco
import numpy as np

from .._data import Sequences
from .._misc import check_positive
from .._progress import AbstractProgressMeter, NoProgressMeter
from ._scenes import load_model
from ._tree import (
    _HINGE,
    _SLIDE,
    Keypoint,
    NotPlanarError,
    Plane,
    build_tree,
    find_plane,
    joint_name,
    name_of,
    reference_data,
    select_keypoints,
)

_ZERO_FRACTION = 0.2  # KeyCLD A.6: no control in 20% of the runs
_DEFAULT_CONTROL_RANGE = (-2.0, 2.0)  # KeyCLD's actions where the scene sets no control range
# MuJoCo's joint-space forces: M(q) qacc + qfrc_bias = qfrc_actuator + qfrc_passive + qfrc_constraint
_FORCES = ("qfrc_passive", "qfrc_actuator", "qfrc_constraint", "qfrc_bias")


# -- what to apply ----------------------------------------------------------------------------------


def _control_range(model: mujoco.MjModel, control_range) -> np.ndarray:
    """`(nu, 2)` bounds for random controls."""
    if control_range is not None:
        bounds = np.broadcast_to(np.asarray(control_range, dtype=float), (model.nu, 2)).copy()
    else:
        bounds = np.tile(np.asarray(_DEFAULT_CONTROL_RANGE), (model.nu, 1))
        limited = model.actuator_ctrllimited.astype(bool)
        bounds[limited] = model.actuator_ctrlrange[limited]
    if np.any(bounds[:, 0] > bounds[:, 1]):
        raise ValueError(f"control_range: lower bounds above upper bounds: {bounds.tolist()}")
    return bounds


def random_controls(
    model: mujoco.MjModel,
    runs: int,
    rng: np.random.Generator,
    *,
    control_range=None,
    zero_fraction: float = _ZERO_FRACTION,
) -> np.ndarray:
    """One constant control per run, uniform in the control range, zero in a fraction of the runs."""
    bounds = _control_range(model, control_range)
    controls = rng.uniform(bounds[:, 0], bounds[:, 1], size=(runs, model.nu))
    zero = rng.permutation(runs)[: int(round(zero_fraction * runs))]
    controls[zero] = 0.0
    return controls


def random_initial_states(
    model: mujoco.MjModel, runs: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """KeyCLD's initial states: hinge angles U(-pi, pi), slide positions U(-1, 1) within their range,
    velocities U(-0.1, 0.1); other joints at `qpos0` and at rest."""
    qpos = np.tile(model.qpos0, (runs, 1))
    qvel = np.zeros((runs, model.nv))
    for j in range(model.njnt):
        adr, dof = model.jnt_qposadr[j], model.jnt_dofadr[j]
        if model.jnt_type[j] == _HINGE:
            qpos[:, adr] = rng.uniform(-np.pi, np.pi, runs)
        elif model.jnt_type[j] == _SLIDE:
            low, high = -1.0, 1.0
            if model.jnt_limited[j]:
                low, high = max(low, model.jnt_range[j, 0]), min(high, model.jnt_range[j, 1])
            qpos[:, adr] = rng.uniform(low, high, runs)
        else:
            continue
        qvel[:, dof] = rng.uniform(-0.1, 0.1, runs)
    return qpos, qvel


def _initial(model, initial, runs, rng) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(initial, str):
        if initial != "random":
            raise ValueError(f"initial must be 'random', None or (qpos, qvel); got {initial!r}")
        return random_initial_states(model, runs, rng)
    if initial is None:
        return np.tile(model.qpos0, (runs, 1)), np.zeros((runs, model.nv))
    try:
        qpos, qvel = initial
    except (TypeError, ValueError) as error:
        raise ValueError("initial must be 'random', None or a pair (qpos, qvel)") from error
    qpos = np.asarray(qpos, dtype=float)
    qvel = np.asarray(qvel, dtype=float)
    qpos = np.broadcast_to(qpos, (runs, model.nq)) if qpos.ndim == 1 else qpos
    qvel = np.broadcast_to(qvel, (runs, model.nv)) if qvel.ndim == 1 else qvel
    if qpos.shape != (runs, model.nq) or qvel.shape != (runs, model.nv):
        raise ValueError(
            f"initial: qpos must have shape ({model.nq},) or ({runs}, {model.nq}) and qvel ({model.nv},) "
            f"or ({runs}, {model.nv}); got {qpos.shape} and {qvel.shape}"
        )
    return qpos, qvel


def _runs(initial, control, runs) -> int:
    candidates = []
    if isinstance(initial, tuple | list) and len(initial) == 2:
        qpos = np.asarray(initial[0])
        if qpos.ndim == 2:
            candidates.append(qpos.shape[0])
    if control is not None and not callable(control) and not isinstance(control, str):
        array = np.asarray(control)
        if array.ndim >= 2:
            candidates.append(array.shape[0])
    if runs is not None:
        candidates.append(int(runs))
    if len(set(candidates)) > 1:
        raise ValueError(f"the number of runs is ambiguous: initial, control and runs say {candidates}")
    result = candidates[0] if candidates else 1
    if result < 1:
        raise ValueError(f"runs must be at least 1, got {result}")
    return result


def _control_source(model, control, runs, samples, rng, control_range):
    """A function `(run, sample, time, qpos, qvel) -> ctrl`."""
    nu = model.nu
    if callable(control):

        def policy(run, sample, time, qpos, qvel):
            value = np.asarray(control(time, qpos.copy(), qvel.copy()), dtype=float).reshape(-1)
            if value.shape != (nu,):
                raise ValueError(f"the control policy returned shape {value.shape}, expected ({nu},)")
            return value

        return policy
    if isinstance(control, str):
        if control != "random":
            raise ValueError(f"control must be 'random', None, an array or a policy; got {control!r}")
        array = random_controls(model, runs, rng, control_range=control_range)[:, None, :]
    elif control is None:
        array = np.zeros((runs, 1, nu))
    else:
        array = np.asarray(control, dtype=float)
        if array.ndim == 0:
            array = np.broadcast_to(array, (nu,))
        if array.ndim == 1:
            array = np.broadcast_to(array, (runs, nu))
        if array.ndim == 2:
            array = array[:, None, :]
        if (
            array.ndim != 3
            or array.shape[0] != runs
            or array.shape[2] != nu
            or array.shape[1] not in (1, samples - 1, samples)
        ):
            raise ValueError(
                f"control must have shape ({nu},), ({runs}, {nu}) or ({runs}, {samples}, {nu}) "
                f"(or {samples - 1} steps); got {np.shape(control)}"
            )

    def lookup(run, sample, time, qpos, qvel):
        return array[run, min(sample, array.shape[1] - 1)]

    return lookup


# -- MuJoCo --------------------------------------------------------------------------------------


def _substeps(dt: float, physics_dt: float | None, timestep: float) -> tuple[int, float]:
    if physics_dt is None:
        steps = max(1, int(np.ceil(dt / timestep - 1e-9)))
    else:
        steps = max(1, int(round(dt / physics_dt)))
        if abs(steps * physics_dt - dt) > 1e-9 * dt:
            raise ValueError(f"dt={dt} must be a whole multiple of physics_dt={physics_dt}")
    return steps, dt / steps


class _Kinematics:
    """Keypoint positions, velocities and accelerations from MuJoCo's point Jacobians."""

    def __init__(self, model, keypoints: Sequence[Keypoint], plane: Plane | None):
        self.model = model
        self.keypoints = keypoints
        self.projection = np.eye(3) if plane is None else plane.basis
        self.jacp = np.zeros((3, model.nv))
        self.jacd = np.zeros((3, model.nv))

    def __call__(self, data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x, xd, xdd = [], [], []
        for keypoint in self.keypoints:
            point = keypoint.position(data)
            mujoco.mj_jac(self.model, data, self.jacp, None, point, keypoint.body)
            mujoco.mj_jacDot(self.model, data, self.jacd, None, point, keypoint.body)
            x.append(point)
            xd.append(self.jacp @ data.qvel)
            xdd.append(self.jacp @ data.qacc + self.jacd @ data.qvel)
        project = self.projection
        return tuple(np.concatenate([project @ v for v in values]) for values in (x, xd, xdd))


def _motors(model) -> np.ndarray:
    """Which actuators are plain motors (force = gain * ctrl), with a non-zero gain."""
    return (
        (model.actuator_dyntype == mujoco.mjtDyn.mjDYN_NONE)
        & (model.actuator_gaintype == mujoco.mjtGain.mjGAIN_FIXED)
        & (model.actuator_biastype == mujoco.mjtBias.mjBIAS_NONE)
        & (model.actuator_gainprm[:, 0] != 0)
    )


class _AppliedCtrl:
    """The control as applied: clamped to `ctrlrange` where `ctrllimited`, and for motors the force
    MuJoCo applied (after its clamping to `forcerange` where `forcelimited`) over the gain, so that
    `gear * gain * u` is the joint force. What the model fixes is read once, not at every sample."""

    def __init__(self, model):
        clamped = not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL
        self.limited = model.actuator_ctrllimited.astype(bool) & clamped
        self.low, self.high = model.actuator_ctrlrange[self.limited].T
        self.gain = model.actuator_gainprm[:, 0].copy()
        self.motors = _motors(model)

    def __call__(self, data, ctrl: np.ndarray) -> np.ndarray:
        applied = ctrl.copy()
        applied[self.limited] = np.clip(ctrl[self.limited], self.low, self.high)
        # where a motor's force was clamped (exact products elsewhere keep the control bit for bit)
        forced = self.motors & (data.actuator_force != self.gain * applied)
        applied[forced] = data.actuator_force[forced] / self.gain[forced]
        return applied


def simulate_mujoco(
    model: mujoco.MjModel,
    keypoints: Sequence[Keypoint],
    plane: Plane | None,
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    controls: Callable,
    samples: int,
    substeps: int,
    *,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> dict[str, np.ndarray]:
    """Step MuJoCo from each initial state and sample every `substeps` steps.

    `u` holds the controls MuJoCo applied (after clamping to `ctrlrange` and, for motors, of their
    force to `forcerange`), `u_commanded` those asked for.
    """
    runs = qpos0.shape[0]
    kinematics, applied = _Kinematics(model, keypoints, plane), _AppliedCtrl(model)
    data = mujoco.MjData(model)
    k = kinematics.projection.shape[0] * len(keypoints)
    out = {
        "qpos": np.zeros((runs, samples, model.nq)),
        "qvel": np.zeros((runs, samples, model.nv)),
        "qacc": np.zeros((runs, samples, model.nv)),
        "x_clean": np.zeros((runs, samples, k)),
        "xd": np.zeros((runs, samples, k)),
        "xdd": np.zeros((runs, samples, k)),
        "u": np.zeros((runs, samples, model.nu)),
        "u_commanded": np.zeros((runs, samples, model.nu)),
        **{name: np.zeros((runs, samples, model.nv)) for name in _FORCES},
        "constraint_rows": np.zeros((runs, samples), dtype=int),
    }
    state = progress_meter.start(runs, desc="MuJoCo runs", unit="run")
    try:
        for r in range(runs):
            _run(model, data, kinematics, applied, out, r, qpos0[r], qvel0[r], controls=controls,
                 samples=samples, substeps=substeps)
            state = progress_meter.update(state, r + 1)
    finally:
        progress_meter.close(state)
    return out


def _run(model, data, kinematics, applied, out, r, qpos0, qvel0, *, controls, samples, substeps) -> None:
    """Run `r`: from `(qpos0, qvel0)`, each sample written into `out[...][r]`."""
    mujoco.mj_resetData(model, data)
    data.qpos[:] = qpos0
    data.qvel[:] = qvel0
    for s in range(samples):
        ctrl = np.asarray(controls(r, s, data.time, data.qpos, data.qvel), dtype=float)
        data.ctrl[:] = ctrl
        mujoco.mj_forward(model, data)
        out["qpos"][r, s] = data.qpos
        out["qvel"][r, s] = data.qvel
        out["qacc"][r, s] = data.qacc
        out["u"][r, s] = applied(data, ctrl)
        out["u_commanded"][r, s] = ctrl
        for name in _FORCES:
            out[name][r, s] = getattr(data, name)
        out["constraint_rows"][r, s] = data.nefc
        out["x_clean"][r, s], out["xd"][r, s], out["xdd"][r, s] = kinematics(data)
        if s + 1 < samples:
            for _ in range(substeps):
                mujoco.mj_step(model, data)


def _integrator(model, integrator: str | None) -> None:
    if integrator is None:
        return
    names = {
        key.removeprefix("mjINT_").lower(): value for key, value in mujoco.mjtIntegrator.__members__.items()
    }
    key = integrator.lower()
    if key not in names:
        raise ValueError(f"unknown integrator {integrator!r}; choose one of {sorted(names)}")
    model.opt.integrator = names[key]


def prepare(model: mujoco.MjModel, keypoints):
    """`(tree, plane or None, keypoints)` for a model: planar keypoints where the model is planar."""
    data = reference_data(model)
    tree = build_tree(model)
    try:
        plane = find_plane(model, data)
    except NotPlanarError:
        plane = None
    return tree, plane, select_keypoints(model, data, tree, plane, keypoints)


def record(
    mjcf: "str | os.PathLike",
    *,
    duration: float,
    dt: float | None = None,
    runs: int | None = None,
    initial="random",
    control="random",
    keypoints: Sequence[str] | None = None,
    noise: float = 0.0,
    seed: int = 0,
    physics_dt: float | None = None,
    integrator: str | None = None,
    control_range=None,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> Sequences:
    """Record trajectories of a MuJoCo scene.

    Each run starts from its initial state and is sampled every `dt` seconds from `t = 0` to
    `duration`; MuJoCo steps `physics_dt` in between, with the controls held from one sample to the
    next. At every sample MuJoCo's own kinematics give the keypoints: positions, velocities
    `J qvel` and accelerations `J qacc + Jdot qvel` of the keypoint points, projected onto the plane
    of motion for planar models.

    **Arguments:**

    - `mjcf`: a path, an XML string, a dm_control suite name or `"keycld/<name>"` (see `scene_xml`).
    - `duration`: length of each run in seconds.
    - `dt`: sampling interval; the model's timestep by default.
    - `runs`: the number of runs; by default inferred from `initial` or `control`, else 1.
    - `initial`: `"random"` (KeyCLD: hinge angles U(-pi, pi), slide positions U(-1, 1), velocities
      U(-0.1, 0.1)), `None` (the model's `qpos0`, at rest), or a pair `(qpos, qvel)` of shapes
      `(nq,)`/`(nv,)` or `(runs, nq)`/`(runs, nv)`.
    - `control`: `"random"` (KeyCLD: one constant control per run, uniform in the control range, zero
      in 20% of the runs), `None` (zero), an array `(nu,)` (the same for every run), `(runs, nu)`
      (constant per run) or `(runs, T, nu)` (a time series, one value per sample), or a feedback
      policy `control(t, qpos, qvel) -> ctrl`, evaluated at each sample.
    - `keypoints`: names of sites to use as keypoints; the defaults of `from_mjcf` otherwise.
    - `noise`: standard deviation (metres) of Gaussian noise added to the keypoint positions `x`;
      `extras["x_clean"]` keeps them exact.
    - `seed`: seeds initial states, controls and noise.
    - `physics_dt`: MuJoCo's step, dividing `dt`; by default the largest step not above the model's
      timestep.
    - `integrator`: `"euler"`, `"rk4"`, `"implicit"` or `"implicitfast"`; the model's by default.
    - `control_range`: `(low, high)` for random controls, or `(nu, 2)` bounds; by default each
      actuator's `ctrlrange` where it is limited and `(-2, 2)` elsewhere (KeyCLD).
    - `progress_meter`: reports the runs as they finish, e.g. `cldyn.TextProgressMeter()`; none by
      default.

    **Returns:** a `cldyn.Sequences` of `R` runs of `T` samples (numpy float64 arrays):

    - `x`: keypoint positions as observed, `(R, T, k)` with `k = d * n_keypoints`, laid out
      `[x1, y1, x2, y2, ...]` (planar, `d = 2`) or `[x1, y1, z1, ...]` (world, `d = 3`, for
      non-planar models), with the noise; `xd`, `xdd`: keypoint velocities and accelerations (exact).
    - `u`: the controls MuJoCo applied from each sample to the next, `(R, T, nu)`: clamped to
      `ctrlrange` where `ctrllimited`, and for motors the force MuJoCo applied (clamped to `forcerange`
      where `forcelimited`) over the gain, so that `gear * gain * u` is the joint force; `dt` the
      sampling interval, `ts` the sample times.
    - `extras`: `qpos` `(R, T, nq)`, `qvel`, `qacc` `(R, T, nv)`; `x_clean` (the positions without
      noise); MuJoCo's joint-space forces `qfrc_passive`, `qfrc_actuator`, `qfrc_constraint`,
      `qfrc_bias` `(R, T, nv)`, with `M(q) qacc + qfrc_bias = qfrc_actuator + qfrc_passive +
      qfrc_constraint`; and `u_commanded`, the controls asked for, only where MuJoCo clamped some.
    - `info`: `keypoint_names`, `joint_names`, `actuator_names` (in column order); `basis`, the
      plane's in-plane unit vectors as rows (planar point = `basis @ world point`; `[]` for world
      keypoints) and `keypoint_dim`; `mjcf` (where the scene came from: path, suite name,
      `keycld/<name>` or `<xml string>`) and `mjcf_xml` (its self-contained XML text); `physics_dt`
      and `integrator` (MuJoCo's step and integrator); `noise`, `seed`.

    !!! example

        ```python
        data = cldyn.mujoco.record("keycld/pendulum", runs=500, duration=0.98, dt=0.02, seed=0)
        data.save("pendulum.npz")
        qpos, joints = data.extras["qpos"], data.info["joint_names"]
        ```
    """
    check_positive("duration", duration, allow_zero=True)
    if dt is not None:
        check_positive("dt", dt)
    if physics_dt is not None:
        check_positive("physics_dt", physics_dt)
    if runs is not None:
        check_positive("runs", runs, integer=True)
    check_positive("noise", noise, allow_zero=True)
    seed = _seed(seed)
    model, xml, source = load_model(mjcf)
    dt = float(model.opt.timestep) if dt is None else float(dt)
    samples = int(round(duration / dt)) + 1
    if abs((samples - 1) * dt - duration) > 1e-9 * max(1.0, duration):
        raise ValueError(f"duration={duration} must be a whole multiple of dt={dt}")
    substeps, step = _substeps(dt, physics_dt, float(model.opt.timestep))
    model.opt.timestep = step
    _integrator(model, integrator)
    _, plane, chosen = prepare(model, keypoints)

    runs = _runs(initial, control, runs)
    initial_seed, control_seed, noise_seed = np.random.SeedSequence(seed).spawn(3)
    qpos0, qvel0 = _initial(model, initial, runs, np.random.default_rng(initial_seed))
    controls = _control_source(
        model, control, runs, samples, np.random.default_rng(control_seed), control_range
    )
    out = simulate_mujoco(
        model, chosen, plane, qpos0, qvel0, controls, samples, substeps, progress_meter=progress_meter
    )
    out.pop("constraint_rows")
    x_clean = out["x_clean"]
    x = x_clean
    if noise > 0:
        x = x_clean + noise * np.random.default_rng(noise_seed).standard_normal(x_clean.shape)
    extras = {name: out[name] for name in ("qpos", "qvel", "qacc", "x_clean", *_FORCES)}
    if not np.array_equal(out["u_commanded"], out["u"]):
        extras["u_commanded"] = out["u_commanded"]
    integrator_name = mujoco.mjtIntegrator(int(model.opt.integrator)).name.removeprefix("mjINT_")
    basis = np.zeros((0, 3)) if plane is None else plane.basis + 0.0
    info = {
        "keypoint_names": [k.name for k in chosen],
        "joint_names": [joint_name(model, j) for j in range(model.njnt)],
        "actuator_names": [
            name_of(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator") for a in range(model.nu)
        ],
        "basis": basis.tolist(),
        "keypoint_dim": 2 if plane is not None else 3,
        "mjcf": source,
        "mjcf_xml": xml,
        "physics_dt": step,
        "integrator": integrator_name,
        "noise": float(noise),
        "seed": seed,
    }
    return Sequences(x, out["u"], dt, xd=out["xd"], xdd=out["xdd"], extras=extras, info=info)


def _seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)
