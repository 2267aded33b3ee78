"""Headless MuJoCo rendering of planar scenes: image datasets in the KeyCLD protocol (paper A.6).

Each run starts from a random state, holds one random control and is simulated by MuJoCo; every
frame is rendered by a fixed camera. Runs are rendered in parallel worker processes (started with
`spawn`, each with its own OpenGL context, `MUJOCO_GL=egl` unless the environment says otherwise).
All randomness is drawn in the calling process from the seed, so the result does not depend on the
number of workers.
"""

import concurrent.futures
import dataclasses
import math
import multiprocessing
import multiprocessing.util
import os
import pathlib
import re
import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np

import cldyn
from cldyn._misc import check_fraction, check_positive, optional_import

from ._data import SCHEMA, Frames, PlanarCamera, cache_directory, cache_key
from ._scene import _HINGE, _JOINT_TYPES, _Camera, _mujoco, _name, _Scene, _scene, default_keypoint_names


@dataclasses.dataclass(frozen=True)
class RenderProtocol:
    """How a dataset is generated: the KeyCLD paper's protocol (appendix A.6 and the authors' code) by
    default.

    **Fields:**

    - `runs`, `frames`: the number of runs and of frames per run (500 x 50).
    - `image_size`: the side of the square RGB frames in pixels (64).
    - `validation_runs`: the last runs, kept for validation (50).
    - `control_limit`: each actuator's constant control is drawn from `U(-c, c)` (2), or from its
      `ctrlrange` where the scene limits it.
    - `zero_control_fraction`: the fraction of runs with zero control (0.2).
    - `angle_limit`: initial hinge angles `U(-a, a)` (pi).
    - `slide_limit`: initial slide positions `U(-s, s)`, within the joint's range (1).
    - `velocity_limit`: initial joint velocities `U(-v, v)` (0.1).
    - `steps_per_frame`: MuJoCo steps between frames (1: the frame interval is the scene's
      timestep: 0.02 s Euler for KeyCLD's pendulum, 0.01 s RK4 for its cart-pole and acrobot).
    - `shadow_size`: the shadow map's size in pixels, or `None` for the scene's (2048 in KeyCLD's
      scenes). 512 renders KeyCLD's scenes at 64 x 64 three to four times faster, but not
      pixel-identically (about one pixel in 10^4 differs, on shadow edges), so the default keeps
      the scene's.
    - `supersample`: each pixel is the mean of `s x s` samples of MuJoCo's render at `s` times the
      size (a camera's pixel integrates light over its area), rounded to 8 bits. 1 (the paper's
      frames) is MuJoCo's render itself, which samples each pixel at 4 points: the edge of a link one
      or two pixels wide then moves the frame in quarter-coverage steps, and an estimator's reading of
      a small turn steps with it (`docs/acrobot_from_frames.md`).

    !!! example

        ```python
        small = keyvision.RenderProtocol(runs=20, frames=10, validation_runs=4)
        frames = keyvision.render("keycld/acrobot", protocol=small)
        ```
    """

    runs: int = 500
    frames: int = 50
    image_size: int = 64
    validation_runs: int = 50
    control_limit: float = 2.0
    zero_control_fraction: float = 0.2
    angle_limit: float = math.pi
    slide_limit: float = 1.0
    velocity_limit: float = 0.1
    steps_per_frame: int = 1
    shadow_size: int | None = None
    supersample: int = 1

    def __post_init__(self):
        check_positive("RenderProtocol: runs", self.runs, integer=True)
        check_positive("RenderProtocol: frames", self.frames, integer=True)
        check_positive("RenderProtocol: image_size", self.image_size, integer=True)
        check_positive("RenderProtocol: validation_runs", self.validation_runs, integer=True, allow_zero=True)
        if self.validation_runs > self.runs:
            raise ValueError(
                f"RenderProtocol: validation_runs ({self.validation_runs}) exceeds runs ({self.runs})"
            )
        for name in ("control_limit", "angle_limit", "slide_limit", "velocity_limit"):
            check_positive(f"RenderProtocol: {name}", getattr(self, name), allow_zero=True)
        check_fraction(
            "RenderProtocol: zero_control_fraction",
            self.zero_control_fraction,
            low_open=False,
            high_open=False,
        )
        check_positive("RenderProtocol: steps_per_frame", self.steps_per_frame, integer=True)
        if self.shadow_size is not None:
            check_positive("RenderProtocol: shadow_size", self.shadow_size, integer=True)
        check_positive("RenderProtocol: supersample", self.supersample, integer=True)


# -- random initial states and controls -------------------------------------------------------------


def _initial_states(model, protocol: RenderProtocol, rng: np.random.Generator):
    runs = protocol.runs
    qpos = np.tile(model.qpos0, (runs, 1))
    qvel = np.zeros((runs, model.nv))
    for j in range(model.njnt):
        adr, dof = model.jnt_qposadr[j], model.jnt_dofadr[j]
        if model.jnt_type[j] == _HINGE:
            qpos[:, adr] = rng.uniform(-protocol.angle_limit, protocol.angle_limit, runs)
        else:
            low, high = -protocol.slide_limit, protocol.slide_limit
            if model.jnt_limited[j]:
                low, high = max(low, model.jnt_range[j, 0]), min(high, model.jnt_range[j, 1])
            qpos[:, adr] = model.qpos0[adr] + rng.uniform(low, high, runs)
        qvel[:, dof] = rng.uniform(-protocol.velocity_limit, protocol.velocity_limit, runs)
    return qpos, qvel


def _controls(model, protocol: RenderProtocol, rng: np.random.Generator) -> np.ndarray:
    bounds = np.tile([-protocol.control_limit, protocol.control_limit], (model.nu, 1)).astype(float)
    limited = model.actuator_ctrllimited.astype(bool)
    bounds[limited] = model.actuator_ctrlrange[limited]
    controls = rng.uniform(bounds[:, 0], bounds[:, 1], size=(protocol.runs, model.nu))
    zero = rng.permutation(protocol.runs)[: int(round(protocol.zero_control_fraction * protocol.runs))]
    controls[zero] = 0.0
    return controls


# -- the worker processes -------------------------------------------------------------------------

_WORKER: dict[str, Any] = {}


def _open(setup: dict) -> dict[str, Any]:
    """Compile the scene and open an offscreen renderer: a GL context of this process."""
    mujoco = _mujoco()
    scene = _scene(setup["xml"], setup["protocol"], setup["camera"], setup["keypoints"])
    renderer = _Camera(mujoco, scene, setup["protocol"])
    return dict(mujoco=mujoco, scene=scene, renderer=renderer, data=mujoco.MjData(scene.model))


def _open_here(setup: dict) -> dict[str, Any]:
    """`_open` in the calling process, whose MuJoCo may have chosen a GL backend that cannot render
    offscreen (it chooses when first imported)."""
    try:
        return _open(setup)
    except Exception as error:
        backend = os.environ.get("MUJOCO_GL", "unset")
        raise RuntimeError(
            f"keyvision.render(workers=1): MuJoCo cannot render in this process ({type(error).__name__}: "
            f"{error}; MUJOCO_GL is {backend}, and MuJoCo chose its backend when first imported). Set "
            "MUJOCO_GL=egl before anything imports mujoco, or render with workers > 1 (processes of their "
            "own, with EGL)."
        ) from error


def _start_worker(setup: dict) -> None:
    """Runs in each worker process: choose the GL backend before MuJoCo is imported, then open the
    worker's scene and renderer."""
    os.environ.setdefault("MUJOCO_GL", setup["gl"])
    _WORKER.update(_open(setup))
    # Close the GL context before the interpreter tears the module down (else its finaliser fails).
    renderer = _WORKER["renderer"]
    multiprocessing.util.Finalize(renderer, renderer.close, exitpriority=10)


def _simulate_and_render(scene: _Scene, renderer, data, mujoco, qpos0, qvel0, ctrl, protocol) -> dict:
    """One run: render frame t from the state at t, then step MuJoCo `steps_per_frame` times."""
    model, count = scene.model, protocol.frames
    out = {
        "frames": np.zeros((count, protocol.image_size, protocol.image_size, 3), np.uint8),
        "qpos": np.zeros((count, model.nq)),
        "qvel": np.zeros((count, model.nv)),
        "keypoints": np.zeros((count, 2 * len(scene.keypoints))),
    }
    mujoco.mj_resetData(model, data)
    data.qpos[:] = qpos0
    data.qvel[:] = qvel0
    data.ctrl[:] = ctrl
    for t in range(count):
        mujoco.mj_forward(model, data)  # kinematics of the current state (mj_step leaves the old one)
        out["qpos"][t] = data.qpos
        out["qvel"][t] = data.qvel
        out["keypoints"][t] = np.concatenate([scene.basis @ point.world(data) for point in scene.keypoints])
        out["frames"][t] = renderer.render(data)
        if t + 1 < count:
            for _ in range(protocol.steps_per_frame):
                mujoco.mj_step(model, data)
    return out


def _render_chunk(task: tuple, state: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
    """Render one chunk of runs with `state` (`_open`'s), a worker's own by default."""
    runs, qpos0, qvel0, ctrl, protocol = task
    state = _WORKER if state is None else state
    outs = [
        _simulate_and_render(
            state["scene"],
            state["renderer"],
            state["data"],
            state["mujoco"],
            qpos0[i],
            qvel0[i],
            ctrl[i],
            protocol,
        )
        for i in range(len(runs))
    ]
    return runs, {name: np.stack([o[name] for o in outs]) for name in outs[0]}


# -- the public entry point -----------------------------------------------------------------------


def _looks_like_xml(scene) -> bool:
    return isinstance(scene, str) and scene.lstrip().startswith("<")


def _scene_xml(scene) -> str:
    if _looks_like_xml(scene):
        try:
            ET.fromstring(scene)
        except ET.ParseError as error:
            raise ValueError(f"scene: not valid XML ({error})") from error
        return scene
    return optional_import("cldyn.mujoco", purpose="keyvision.render").scene_xml(scene)


def _slug(scene) -> str:
    if isinstance(scene, str) and not _looks_like_xml(scene):
        stem = pathlib.Path(scene).stem if scene.endswith((".xml", ".mjcf")) else scene
        return re.sub(r"[^A-Za-z0-9]+", "-", stem).strip("-") or "scene"
    if isinstance(scene, os.PathLike):
        return re.sub(r"[^A-Za-z0-9]+", "-", pathlib.Path(scene).stem).strip("-") or "scene"
    return "scene"


def render(
    scene: "str | os.PathLike",
    *,
    camera: str | int = "fixed",
    protocol: RenderProtocol = RenderProtocol(),
    seed: int = 0,
    keypoints: Sequence[str] | None = None,
    cache: "bool | str | os.PathLike" = True,
    workers: int | None = None,
    progress_meter: cldyn.AbstractProgressMeter = cldyn.NoProgressMeter(),
) -> Frames:
    """Render an image dataset of a planar MuJoCo scene: random runs seen by a fixed camera.

    Each run starts from a random state (hinge angles `U(-pi, pi)`, slide positions `U(-1, 1)`,
    velocities `U(-0.1, 0.1)`), holds one random control (`U(-2, 2)` per actuator, zero in 20% of
    the runs) and is simulated by MuJoCo, one step per frame with the scene's timestep and
    integrator; each frame is rendered headless. The ground truth (joint states, keypoints in metres,
    the camera's pixel-to-plane map) is stored beside the frames.

    The result is cached under a hash of the scene's XML, the camera, the protocol, the keypoints,
    the seed and MuJoCo's version: a later call with the same request loads it. A cached file that
    is unreadable or was made for another request raises an error naming the file (delete it, or
    pass `cache=False`), never a silent re-use or re-render.

    **Arguments:**

    - `scene`: an MJCF path, an XML string, a dm_control suite name or `"keycld/<name>"` (anything
      `cldyn.mujoco.scene_xml` accepts).
    - `camera`: the name or index of a camera fixed in the world (`"fixed"`: the KeyCLD cameras).
    - `protocol`: a `RenderProtocol`: runs, frames, image size and random distributions.
    - `seed`: seeds the initial states and the controls; the frames depend on nothing else.
    - `keypoints`: names of sites whose positions are the ground-truth keypoints; by default the
      moving joint anchors and the far ends of the terminal bodies and of every turning body that
      no other body is hinged to (KeyCLD's keypoints in KeyCLD's scenes).
    - `cache`: `True` for `keyvision.cache_directory()`, a directory, or `False` for none.
    - `workers`: the number of worker processes (the number of CPUs by default). Workers are
      started with 'spawn' and import the calling script again, whose code must then sit under
      `if __name__ == "__main__":`; `workers=1` renders in the calling process instead.
    - `progress_meter`: a `cldyn.AbstractProgressMeter`, e.g. `cldyn.TextProgressMeter()`.

    **Returns:** a `keyvision.Frames`.

    !!! example

        ```python
        frames = keyvision.render("keycld/pendulum", seed=0, progress_meter=cldyn.TextProgressMeter())
        frames.frames.shape     # (500, 50, 64, 64, 3)
        ```
    """
    if not isinstance(protocol, RenderProtocol):
        raise TypeError(f"protocol must be a keyvision.RenderProtocol, got {type(protocol).__name__}")
    check_positive("seed", seed, integer=True, allow_zero=True)
    if workers is not None:
        check_positive("workers", workers, integer=True)
    if keypoints is not None:
        keypoints = (keypoints,) if isinstance(keypoints, str) else tuple(keypoints)
    mujoco = _mujoco()
    xml = _scene_xml(scene)
    request = {
        "schema": SCHEMA,
        "xml": xml,
        "camera": camera,
        "protocol": _protocol_fields(protocol),
        "seed": int(seed),
        "keypoints": keypoints,
        "mujoco": mujoco.__version__,
    }
    key = cache_key(request)
    path = None
    if cache is not False:
        directory = cache_directory() if cache is True else pathlib.Path(cache)
        path = directory / f"{_slug(scene)}-{key[:16]}.npz"
        if path.exists():
            frames = _load_cached(path, key)
            if keypoints is None:  # the default keypoints gained the ends of turning bodies on 2026-12-03
                default = default_keypoint_names(xml)
                names = frames.info.get("keypoint_names")
                if names is not None and list(names) != default:
                    raise ValueError(
                        f"{path}: the cached frames have the keypoints {frames.info.get('keypoint_names')}, "
                        f"the scene's default keypoints are now {default}; delete the file to render again, "
                        "or pass cache=False."
                    )
            return frames
    setup = {"xml": xml, "protocol": protocol, "camera": camera, "keypoints": keypoints, "gl": "egl"}
    start = time.perf_counter()
    frames = _render(setup, seed, workers, progress_meter)
    elapsed = time.perf_counter() - start
    info = {
        **frames.info,
        "scene": "<xml>" if _looks_like_xml(scene) else str(scene),
        "camera": camera,
        "seed": int(seed),
        "cache_key": key,
        "render_seconds": round(elapsed, 3),
    }
    frames = dataclasses.replace(frames, info=info)
    if path is not None:
        frames.save(path)
    return frames


def _protocol_fields(protocol: RenderProtocol) -> dict:
    """The protocol as its cache key and the frames' info hold it: fields added to `RenderProtocol`
    after caches were written are left out at their default, so those caches keep their keys."""
    fields = dataclasses.asdict(protocol)
    if protocol.supersample == 1:
        del fields["supersample"]
    return fields


def _load_cached(path: pathlib.Path, key: str) -> Frames:
    try:
        frames = Frames.load(path)
    except (ValueError, OSError) as error:
        raise ValueError(
            f"{error}\nThe cached frames at {path} are unusable: delete the file to render again, or "
            "pass cache=False."
        ) from error
    if frames.info.get("cache_key") != key:
        raise ValueError(
            f"{path}: the cached frames were rendered for another request (cache key "
            f"{frames.info.get('cache_key')!r}, expected {key!r}); delete the file to render again, or "
            "pass cache=False."
        )
    return frames


def _render(setup: dict, seed: int, workers: int | None, progress_meter) -> Frames:
    mujoco = _mujoco()
    protocol: RenderProtocol = setup["protocol"]
    scene = _scene(setup["xml"], protocol, setup["camera"], setup["keypoints"])
    model = scene.model
    initial_seed, control_seed = np.random.SeedSequence(seed).spawn(2)
    qpos0, qvel0 = _initial_states(model, protocol, np.random.default_rng(initial_seed))
    controls = _controls(model, protocol, np.random.default_rng(control_seed))

    runs = protocol.runs
    workers = min(workers or os.cpu_count() or 1, runs)
    chunk = max(1, min(10, math.ceil(runs / (4 * workers))))
    tasks = [
        (
            np.arange(s, min(s + chunk, runs)),
            qpos0[s : s + chunk],
            qvel0[s : s + chunk],
            controls[s : s + chunk],
            protocol,
        )
        for s in range(0, runs, chunk)
    ]
    size = protocol.image_size
    out = {
        "frames": np.zeros((runs, protocol.frames, size, size, 3), np.uint8),
        "qpos": np.zeros((runs, protocol.frames, model.nq)),
        "qvel": np.zeros((runs, protocol.frames, model.nv)),
        "keypoints": np.zeros((runs, protocol.frames, 2 * len(scene.keypoints))),
    }
    state = progress_meter.start(runs, desc="render", unit="run")
    done = 0

    def collect(indices, result) -> None:
        nonlocal state, done
        for name, value in result.items():
            out[name][indices] = value
        done += len(indices)
        state = progress_meter.update(state, done)

    context = multiprocessing.get_context("spawn")
    try:
        if workers == 1:  # in this process: no process to start, and no script imported again
            own = _open_here(setup)
            try:
                for task in tasks:
                    collect(*_render_chunk(task, own))
            finally:
                own["renderer"].close()
        else:
            with concurrent.futures.ProcessPoolExecutor(
                workers, mp_context=context, initializer=_start_worker, initargs=(setup,)
            ) as pool:
                for future in concurrent.futures.as_completed([pool.submit(_render_chunk, t) for t in tasks]):
                    collect(*future.result())
    except BrokenProcessPool as error:
        raise RuntimeError(
            "keyvision.render: a rendering worker process died (its error is printed above). Workers are "
            "started with 'spawn' and import the calling script again: guard a script's code with "
            "`if __name__ == '__main__':`, or pass workers=1 to render in the calling process. Check also "
            "that MuJoCo can render headless (MUJOCO_GL=egl)."
        ) from error
    finally:
        progress_meter.close(state)
    timestep = float(model.opt.timestep)
    integrator = mujoco.mjtIntegrator(int(model.opt.integrator)).name.removeprefix("mjINT_")
    info = {
        "mjcf_xml": setup["xml"],
        "protocol": _protocol_fields(protocol),
        "keypoint_names": [point.name for point in scene.keypoints],
        "joint_names": [
            _name(mujoco, model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint") for j in range(model.njnt)
        ],
        "joint_types": [_JOINT_TYPES[int(t)] for t in model.jnt_type],
        "joint_qpos_index": [int(a) for a in model.jnt_qposadr],
        "actuator_names": [
            _name(mujoco, model, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator") for a in range(model.nu)
        ],
        "timestep": timestep,
        "integrator": integrator,
        "validation_runs": protocol.validation_runs,
        "mujoco": mujoco.__version__,
    }
    return Frames(
        frames=out["frames"],
        u=np.repeat(controls[:, None, :], protocol.frames, axis=1),
        dt=timestep * protocol.steps_per_frame,
        extras={"qpos": out["qpos"], "qvel": out["qvel"], "keypoints": out["keypoints"]},
        camera=PlanarCamera(scene.homography, scene.basis),
        info=info,
    )


def render_poses(
    scene: "str | os.PathLike",
    qpos: "np.ndarray",
    *,
    camera: str | int = "fixed",
    image_size: int = 64,
    keypoints: Sequence[str] | None = None,
    supersample: int = 1,
) -> dict[str, np.ndarray]:
    """Render a scene in given joint positions, with MuJoCo's potential energy of each pose.

    For sequences of poses chosen by hand (a link turned through a full circle, a cart moved along
    its rail) rather than simulated runs: the learnt potential of a model along them can be set
    beside the true one (the KeyCLD paper's figures 8-12). Rendered as `keyvision.render` renders,
    in this process, nothing cached.

    **Arguments:**

    - `scene`: what `keyvision.render` accepts (`"keycld/pendulum"`, an MJCF, ...).
    - `qpos`: `(N, nq)` joint positions, MuJoCo's `qpos` layout.
    - `camera`, `keypoints`: as in `keyvision.render`.
    - `image_size`: the side of the square frames in pixels.
    - `supersample`: samples per pixel along each side (`keyvision.RenderProtocol`).

    **Returns:** a dict with `frames` `(N, H, W, 3)` uint8, `keypoints` `(N, 2K)` the ground-truth
    keypoints in metres in the plane of motion (as `keyvision.render` stores them) and `potential`
    `(N,)` MuJoCo's potential energy (gravity and springs) in joules.

    !!! example

        ```python
        angles = np.linspace(0, 2 * np.pi, 73)
        poses = keyvision.render_poses("keycld/pendulum", angles[:, None])
        ```
    """
    check_positive("image_size", image_size, integer=True)
    if keypoints is not None:
        keypoints = (keypoints,) if isinstance(keypoints, str) else tuple(keypoints)
    mujoco = _mujoco()
    protocol = RenderProtocol(
        runs=1, frames=1, validation_runs=0, image_size=image_size, supersample=supersample
    )
    setup = _scene(_scene_xml(scene), protocol, camera, keypoints)
    model = setup.model
    qpos = np.asarray(qpos, dtype=float)
    if qpos.ndim != 2 or qpos.shape[1] != model.nq:
        raise ValueError(f"render_poses: qpos must be (N, {model.nq}) for this scene, got {qpos.shape}")
    if not np.all(np.isfinite(qpos)):
        raise ValueError("render_poses: qpos has NaN or infinite entries")
    model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    data = mujoco.MjData(model)
    renderer = _Camera(mujoco, setup, protocol)
    out = {
        "frames": np.zeros((len(qpos), image_size, image_size, 3), np.uint8),
        "keypoints": np.zeros((len(qpos), 2 * len(setup.keypoints))),
        "potential": np.zeros(len(qpos)),
    }
    try:
        for i, pose in enumerate(qpos):
            data.qpos[:] = pose
            data.qvel[:] = 0.0
            mujoco.mj_forward(model, data)
            out["potential"][i] = data.energy[0]
            points = [setup.basis @ point.world(data) for point in setup.keypoints]
            out["keypoints"][i] = np.concatenate(points)
            out["frames"][i] = renderer.render(data)
    finally:
        renderer.close()
    return out
