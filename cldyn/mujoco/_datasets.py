"""KeyCLD's datasets in keypoint coordinates, recorded from the KeyCLD scenes (paper appendix A.6).

The protocol of the paper and of its authors' code: 500 runs of 50 frames (the first 450 train, the
last 50 validate), one physics step per frame (0.02 s with Euler for the pendulum, 0.01 s with RK4
for the cartpole and the acrobot), initial angles U(-pi, pi) and cart positions U(-1, 1), initial
velocities U(-0.1, 0.1), one constant control per run U(-2, 2) per actuator, zero in 20% of the runs.
The keypoints are those of the paper (pendulum: the pole tip; cartpole: the cart and the pole tip;
acrobot: the elbow and the tip), expressed relative to the first joint's anchor, the point the
paper's cameras centre on, so that the paper's constraints (`cldyn.keycld_constraint`) hold with the
pivot at the origin.
"""

import dataclasses
import os
import pathlib
import warnings

import mujoco
import numpy as np

from .._data import Sequences
from .._keycld import KEYCLD_SCENES
from .._misc import check_positive
from .._progress import AbstractProgressMeter, NoProgressMeter
from ._record import record
from ._scenes import keycld_scene
from ._tree import find_plane, reference_data

# (sampling interval = MuJoCo step, MuJoCo integrator of the scene) per scene, as in the authors' code
_PROTOCOL = {"pendulum": (0.02, "EULER"), "cartpole": (0.01, "RK4"), "acrobot": (0.01, "RK4")}
_CACHE_ENV = "CLDYN_CACHE"


def _scene(name: str) -> str:
    key = name.removeprefix("keycld/")
    if key not in _PROTOCOL:
        raise ValueError(f"unknown KeyCLD scene {name!r}; choose one of {', '.join(KEYCLD_SCENES)}")
    return key


def keycld_origin(scene: str) -> np.ndarray:
    """The anchor of the scene's first joint in plane coordinates: the pivot (pendulum, acrobot) or
    the cart's rail height (cartpole); keypoints of `keycld_dataset` are relative to it."""
    model = mujoco.MjModel.from_xml_string(keycld_scene(_scene(scene)))
    data = reference_data(model)
    return find_plane(model, data).project(data.xanchor[0])


def cache_directory() -> pathlib.Path:
    """Where generated datasets are cached: `$CLDYN_CACHE/datasets`, or `~/.cache/cldyn/datasets`."""
    root = os.environ.get(_CACHE_ENV)
    base = pathlib.Path(root) if root else pathlib.Path.home() / ".cache" / "cldyn"
    return base / "datasets"


def _matches(data: Sequences, *, scene, runs, frames, noise, seed, dt) -> bool:
    info = data.info
    return (
        data.num_runs == runs
        and data.num_samples == frames
        and info.get("mjcf") == f"keycld/{scene}"
        and info.get("seed") == seed
        and isinstance(info.get("noise"), float | int)
        and abs(info["noise"] - noise) <= 1e-12
        and abs(data.dt - dt) <= 1e-12
        and all(name in data.extras for name in ("qpos", "x_clean"))
    )


def keycld_recording(
    scene: str,
    *,
    runs: int = 500,
    frames: int = 50,
    noise: float = 0.0,
    seed: int = 0,
    cache: "bool | str | os.PathLike" = True,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> Sequences:
    """Record a KeyCLD dataset with MuJoCo in the paper's protocol (appendix A.6), with a disk cache.

    **Arguments:**

    - `scene`: `"pendulum"`, `"cartpole"` or `"acrobot"` (the fully actuated KeyCLD variants).
    - `runs`, `frames`: the number of runs and of frames per run (500 and 50 in the paper).
    - `noise`: standard deviation (metres) of Gaussian noise on the keypoint positions.
    - `seed`: seeds the initial states, the controls and the noise; recorded in the result.
    - `cache`: `True` for `cache_directory()`, a directory, or `False` for no cache. A cached file
      that is corrupt or does not match the request is regenerated, with a warning; files are
      written atomically, so an interrupted run never leaves half a file.
    - `progress_meter`: reports MuJoCo's runs while recording (e.g. `cldyn.TextProgressMeter()`).

    **Returns:** what `cldyn.mujoco.record` returns (a `cldyn.Sequences` in world-plane
    coordinates, with MuJoCo's joint states and forces in `extras`).

    !!! example

        ```python
        data = cldyn.mujoco.keycld_recording("pendulum", runs=50, seed=1)
        angles = data.extras["qpos"][..., 0]
        ```
    """
    key = _scene(scene)
    dt, integrator = _PROTOCOL[key]
    check_positive("runs", runs, integer=True)
    check_positive("noise", noise, allow_zero=True)
    if check_positive("frames", frames, integer=True) < 3:
        raise ValueError(f"frames must be at least 3, got {frames}")
    path = None
    if cache is not False:
        directory = cache_directory() if cache is True else pathlib.Path(cache)
        path = directory / f"keycld-{key}-runs{runs}-frames{frames}-noise{noise:g}-seed{seed}.npz"
        if path.exists():
            try:
                data = Sequences.load(path)
            except (ValueError, OSError) as error:
                warnings.warn(f"{path}: unreadable cached dataset ({error}); regenerating it", stacklevel=2)
            else:
                if _matches(data, scene=key, runs=runs, frames=frames, noise=noise, seed=seed, dt=dt):
                    return data
                warnings.warn(f"{path}: cached dataset does not match; regenerating it", stacklevel=2)
    data = record(
        f"keycld/{key}",
        runs=runs,
        duration=(frames - 1) * dt,
        dt=dt,
        physics_dt=dt,
        noise=noise,
        seed=seed,
        progress_meter=progress_meter,
    )
    if data.info["integrator"] != integrator:
        raise RuntimeError(
            f"the keycld/{key} scene integrates with {data.info['integrator']}, but KeyCLD's protocol uses "
            f"{integrator}"
        )
    if path is not None:
        data.save(path, overwrite=True)  # replaces only a cache file found unreadable or stale above
    return data


def keycld_dataset(
    scene: str,
    *,
    runs: int = 500,
    frames: int = 50,
    noise: float = 0.0,
    seed: int = 0,
    cache: "bool | str | os.PathLike" = True,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> Sequences:
    """A KeyCLD dataset: keypoint states relative to the scene's first joint, ready for learning.

    The runs of `keycld_recording` (same arguments) shifted by `keycld_origin(scene)`
    (`Sequences.relative_to`), so that the constraints of `cldyn.keycld_constraint(scene)` apply:
    positions `x`, controls `u`, MuJoCo's keypoint velocities `xd` and accelerations `xdd`, and the
    recording's `info` (with `origin`); MuJoCo's joint states and forces (`extras`) stay with
    `keycld_recording`. Split it as the paper does with `data.split(450)`.

    !!! example

        ```python
        data = cldyn.mujoco.keycld_dataset("acrobot", seed=0)      # 500 runs x 50 frames, dt 0.01
        train, validation = data.split(450)
        model = cldyn.keycld_model(4, 2, cldyn.keycld_constraint("acrobot"), key=key)
        ```
    """
    recording = keycld_recording(
        scene, runs=runs, frames=frames, noise=noise, seed=seed, cache=cache, progress_meter=progress_meter
    )
    return dataclasses.replace(recording.relative_to(keycld_origin(scene)), extras={})
