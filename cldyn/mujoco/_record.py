"""`record`: trajectories of a MuJoCo scene, in joint and keypoint coordinates, with MuJoCo's forces.

MuJoCo itself computes everything recorded: keypoint velocities from the point Jacobians
(`mj_jac`), accelerations from `J qacc + Jdot qvel` (`mj_jacDot`).
"""

import dataclasses
import json
import os
import pathlib
import zipfile
from collections.abc import Callable, Sequence

import mujoco
import numpy as np

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

SCHEMA = "cldyn.mujoco.Recording/1"
_ZERO_FRACTION = 0.2  # KeyCLD A.6: no control in 20% of the runs
_DEFAULT_CONTROL_RANGE = (-2.0, 2.0)  # KeyCLD's actions where the scene sets no control range
_ARRAYS = (
    "time",
    "qpos",
    "qvel",
    "qacc",
    "x",
    "x_clean",
    "xd",
    "xdd",
    "u",
    "qfrc_passive",
    "qfrc_actuator",
    "qfrc_constraint",
    "qfrc_bias",
)


@dataclasses.dataclass(frozen=True, eq=False)
class Recording:
    """Trajectories recorded from MuJoCo, batch-first: `R` runs of `T` samples.

    **Fields** (arrays are numpy, float64):

    - `time`: sample times from 0, shape `(T,)`.
    - `qpos`, `qvel`, `qacc`: MuJoCo's joint positions `(R, T, nq)`, velocities and accelerations
      `(R, T, nv)`.
    - `x`: keypoint positions as observed, `(R, T, k)` with `k = d * n_keypoints`, laid out
      `[x1, y1, x2, y2, ...]` (planar, `d = 2`) or `[x1, y1, z1, ...]` (world, `d = 3`, for
      non-planar models); Gaussian noise of standard deviation `noise` added.
    - `x_clean`: the same without noise.
    - `xd`, `xdd`: keypoint velocities and accelerations (without noise).
    - `u`: the controls applied from each sample to the next, after MuJoCo's clamping to
      `ctrlrange`, `(R, T, nu)`.
    - `qfrc_passive`, `qfrc_actuator`, `qfrc_constraint`, `qfrc_bias`: MuJoCo's joint-space
      forces, `(R, T, nv)`; `M(q) qacc + qfrc_bias = qfrc_actuator + qfrc_passive +
      qfrc_constraint`.
    - `keypoint_names`, `joint_names`, `actuator_names`: the names, in column order.
    - `basis`: for planar keypoints the plane's in-plane unit vectors as rows, `(2, 3)` (planar
      point = `basis @ world point`); `(0, 3)` for world keypoints.
    - `mjcf`: where the scene came from (path, suite name, `keycld/<name>` or `<xml string>`).
    - `mjcf_xml`: the scene's self-contained XML text.
    - `dt`: the sampling interval; `physics_dt` and `integrator`: MuJoCo's step and integrator.
    - `noise`: the standard deviation of the position noise (metres); `seed`: the random seed.
    """

    time: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    qacc: np.ndarray
    x: np.ndarray
    x_clean: np.ndarray
    xd: np.ndarray
    xdd: np.ndarray
    u: np.ndarray
    qfrc_passive: np.ndarray
    qfrc_actuator: np.ndarray
    qfrc_constraint: np.ndarray
    qfrc_bias: np.ndarray
    keypoint_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    actuator_names: tuple[str, ...]
    basis: np.ndarray
    mjcf: str
    mjcf_xml: str
    dt: float
    physics_dt: float
    integrator: str
    noise: float
    seed: int

    @property
    def num_runs(self) -> int:
        """The number `R` of runs."""
        return self.qpos.shape[0]

    @property
    def num_samples(self) -> int:
        """The number `T` of samples per run."""
        return self.time.shape[0]

    @property
    def keypoint_dim(self) -> int:
        """The dimension `d` of each keypoint: 2 for planar, 3 for world coordinates."""
        return 2 if self.basis.shape[0] == 2 else 3

    def _metadata(self) -> dict:
        return {
            "schema": SCHEMA,
            "keypoint_names": list(self.keypoint_names),
            "joint_names": list(self.joint_names),
            "actuator_names": list(self.actuator_names),
            "mjcf": self.mjcf,
            "mjcf_xml": self.mjcf_xml,
            "dt": self.dt,
            "physics_dt": self.physics_dt,
            "integrator": self.integrator,
            "noise": self.noise,
            "seed": self.seed,
        }

    def save(self, path: "str | os.PathLike") -> pathlib.Path:
        """Save to a compressed `.npz` file (schema in docs/mujoco.md).

        **Arguments:**

        - `path`: the file; `.npz` is appended if missing.

        **Returns:** the path written.
        """
        path = pathlib.Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {name: getattr(self, name) for name in _ARRAYS}
        np.savez_compressed(path, basis=self.basis, metadata=np.array(json.dumps(self._metadata())), **arrays)
        return path

    @classmethod
    def load(cls, path: "str | os.PathLike") -> "Recording":
        """Load a recording saved by `save`.

        **Arguments:**

        - `path`: the `.npz` file.

        **Returns:** the `Recording`. A missing, corrupt or foreign file raises an error that names
        the file and the problem.
        """
        path = pathlib.Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such recording")
        try:
            with np.load(path, allow_pickle=False) as npz:
                contents = {name: npz[name] for name in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as error:
            raise ValueError(f"{path}: not a readable .npz file ({error})") from error
        if "metadata" not in contents:
            raise ValueError(f"{path}: not a cldyn recording (no metadata entry)")
        try:
            metadata = json.loads(str(contents["metadata"]))
        except json.JSONDecodeError as error:
            raise ValueError(f"{path}: corrupt metadata ({error})") from error
        if metadata.get("schema") != SCHEMA:
            raise ValueError(f"{path}: schema {metadata.get('schema')!r}, expected {SCHEMA!r}")
        missing = [name for name in (*_ARRAYS, "basis") if name not in contents]
        if missing:
            raise ValueError(f"{path}: missing arrays {missing}")
        try:
            recording = cls(
                **{name: np.asarray(contents[name], dtype=float) for name in _ARRAYS},
                basis=np.asarray(contents["basis"], dtype=float).reshape(-1, 3),
                keypoint_names=tuple(metadata["keypoint_names"]),
                joint_names=tuple(metadata["joint_names"]),
                actuator_names=tuple(metadata["actuator_names"]),
                mjcf=str(metadata["mjcf"]),
                mjcf_xml=str(metadata["mjcf_xml"]),
                dt=float(metadata["dt"]),
                physics_dt=float(metadata["physics_dt"]),
                integrator=str(metadata["integrator"]),
                noise=float(metadata["noise"]),
                seed=int(metadata["seed"]),
            )
        except KeyError as error:
            raise ValueError(f"{path}: metadata lacks {error}") from error
        recording.check(where=str(path))
        return recording

    def check(self, *, where: str = "recording") -> None:
        """Raise a `ValueError` naming the problem if the arrays' shapes disagree."""
        runs, samples = self.qpos.shape[:2] if self.qpos.ndim == 3 else (None, None)
        d = self.keypoint_dim
        k = d * len(self.keypoint_names)
        nv, nu = self.qvel.shape[-1] if self.qvel.ndim == 3 else None, len(self.actuator_names)
        expected = {
            "time": (samples,),
            "qvel": (runs, samples, nv),
            "qacc": (runs, samples, nv),
            "x": (runs, samples, k),
            "x_clean": (runs, samples, k),
            "xd": (runs, samples, k),
            "xdd": (runs, samples, k),
            "u": (runs, samples, nu),
            "qfrc_passive": (runs, samples, nv),
            "qfrc_actuator": (runs, samples, nv),
            "qfrc_constraint": (runs, samples, nv),
            "qfrc_bias": (runs, samples, nv),
        }
        if runs is None:
            raise ValueError(f"{where}: qpos must have shape (runs, samples, nq), got {self.qpos.shape}")
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"{where}: {name} has shape {getattr(self, name).shape}, expected {shape}")


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


def _applied_ctrl(model, ctrl: np.ndarray) -> np.ndarray:
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL:
        return ctrl
    limited = model.actuator_ctrllimited.astype(bool)
    clamped = ctrl.copy()
    clamped[limited] = np.clip(ctrl[limited], *model.actuator_ctrlrange[limited].T)
    return clamped


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
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """Step MuJoCo from each initial state and sample every `substeps` steps."""
    runs = qpos0.shape[0]
    kinematics = _Kinematics(model, keypoints, plane)
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
        **{
            name: np.zeros((runs, samples, model.nv))
            for name in ("qfrc_passive", "qfrc_actuator", "qfrc_constraint", "qfrc_bias")
        },
        "constraint_rows": np.zeros((runs, samples), dtype=int),
    }
    iterator = range(runs)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="MuJoCo runs", unit="run")
    for r in iterator:
        mujoco.mj_resetData(model, data)
        data.qpos[:] = qpos0[r]
        data.qvel[:] = qvel0[r]
        for s in range(samples):
            ctrl = controls(r, s, data.time, data.qpos, data.qvel)
            data.ctrl[:] = ctrl
            mujoco.mj_forward(model, data)
            out["qpos"][r, s] = data.qpos
            out["qvel"][r, s] = data.qvel
            out["qacc"][r, s] = data.qacc
            out["u"][r, s] = _applied_ctrl(model, np.asarray(ctrl, dtype=float))
            for name in ("qfrc_passive", "qfrc_actuator", "qfrc_constraint", "qfrc_bias"):
                out[name][r, s] = getattr(data, name)
            out["constraint_rows"][r, s] = data.nefc
            out["x_clean"][r, s], out["xd"][r, s], out["xdd"][r, s] = kinematics(data)
            if s + 1 < samples:
                for _ in range(substeps):
                    mujoco.mj_step(model, data)
    return out


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
    progress: bool = False,
) -> Recording:
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
      `x_clean` keeps them exact.
    - `seed`: seeds initial states, controls and noise.
    - `physics_dt`: MuJoCo's step, dividing `dt`; by default the largest step not above the model's
      timestep.
    - `integrator`: `"euler"`, `"rk4"`, `"implicit"` or `"implicitfast"`; the model's by default.
    - `control_range`: `(low, high)` for random controls, or `(nu, 2)` bounds; by default each
      actuator's `ctrlrange` where it is limited and `(-2, 2)` elsewhere (KeyCLD).
    - `progress`: show a progress bar.

    **Returns:** a `Recording`.

    !!! example

        ```python
        data = cldyn.mujoco.record("keycld/pendulum", runs=500, duration=0.98, dt=0.02, seed=0)
        data.save("pendulum.npz")
        ```
    """
    model, xml, source = load_model(mjcf)
    dt = float(model.opt.timestep) if dt is None else float(dt)
    if not dt > 0 or not duration >= 0:
        raise ValueError(f"need dt > 0 and duration >= 0, got dt={dt}, duration={duration}")
    samples = int(round(duration / dt)) + 1
    if abs((samples - 1) * dt - duration) > 1e-9 * max(1.0, duration):
        raise ValueError(f"duration={duration} must be a whole multiple of dt={dt}")
    if noise < 0:
        raise ValueError(f"noise must be non-negative, got {noise}")
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
    out = simulate_mujoco(model, chosen, plane, qpos0, qvel0, controls, samples, substeps, progress=progress)
    out.pop("constraint_rows")
    x = out["x_clean"]
    if noise > 0:
        x = x + noise * np.random.default_rng(noise_seed).standard_normal(x.shape)
    integrator_name = mujoco.mjtIntegrator(int(model.opt.integrator)).name.removeprefix("mjINT_")
    return Recording(
        time=np.arange(samples) * dt,
        x=x,
        **out,
        keypoint_names=tuple(k.name for k in chosen),
        joint_names=tuple(joint_name(model, j) for j in range(model.njnt)),
        actuator_names=tuple(
            name_of(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator") for a in range(model.nu)
        ),
        basis=np.zeros((0, 3)) if plane is None else plane.basis + 0.0,
        mjcf=source,
        mjcf_xml=xml,
        dt=dt,
        physics_dt=step,
        integrator=integrator_name,
        noise=float(noise),
        seed=int(seed),
    )
