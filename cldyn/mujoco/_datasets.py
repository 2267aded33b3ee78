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

import os
import pathlib
import warnings

import mujoco
import numpy as np

from .._learn import Sequences
from ._record import Recording, record
from ._scenes import keycld_scene
from ._tree import find_plane, reference_data

KEYCLD_SCENES = ("pendulum", "cartpole", "acrobot")
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


def _matches(recording: Recording, runs, frames, noise, seed, dt) -> bool:
    return (
        recording.num_runs == runs
        and recording.num_samples == frames
        and recording.seed == seed
        and abs(recording.noise - noise) <= 1e-12
        and abs(recording.dt - dt) <= 1e-12
    )


def keycld_recording(
    scene: str,
    *,
    runs: int = 500,
    frames: int = 50,
    noise: float = 0.0,
    seed: int = 0,
    cache: "bool | str | os.PathLike" = True,
    progress: bool = False,
) -> Recording:
    """Record a KeyCLD dataset with MuJoCo in the paper's protocol (appendix A.6), with a disk cache.

    **Arguments:**

    - `scene`: `"pendulum"`, `"cartpole"` or `"acrobot"` (the fully actuated KeyCLD variants).
    - `runs`, `frames`: the number of runs and of frames per run (500 and 50 in the paper).
    - `noise`: standard deviation (metres) of Gaussian noise on the keypoint positions.
    - `seed`: seeds the initial states, the controls and the noise; recorded in the result.
    - `cache`: `True` for `cache_directory()`, a directory, or `False` for no cache. A cached file
      that is corrupt or does not match the request is regenerated, with a warning.
    - `progress`: show a progress bar while recording.

    **Returns:** a `cldyn.mujoco.Recording` in world-plane coordinates.
    """
    key = _scene(scene)
    dt, integrator = _PROTOCOL[key]
    if runs < 1 or frames < 3 or noise < 0:
        raise ValueError(f"need runs >= 1, frames >= 3 and noise >= 0; got {runs}, {frames}, {noise}")
    path = None
    if cache is not False:
        directory = cache_directory() if cache is True else pathlib.Path(cache)
        path = directory / f"keycld-{key}-runs{runs}-frames{frames}-noise{noise:g}-seed{seed}.npz"
        if path.exists():
            try:
                recording = Recording.load(path)
            except (ValueError, OSError) as error:
                warnings.warn(f"{path}: unreadable cached dataset ({error}); regenerating it", stacklevel=2)
            else:
                if _matches(recording, runs, frames, noise, seed, dt):
                    return recording
                warnings.warn(f"{path}: cached dataset does not match; regenerating it", stacklevel=2)
    recording = record(
        f"keycld/{key}",
        runs=runs,
        duration=(frames - 1) * dt,
        dt=dt,
        physics_dt=dt,
        noise=noise,
        seed=seed,
        progress=progress,
    )
    if recording.integrator != integrator:
        raise RuntimeError(
            f"the keycld/{key} scene integrates with {recording.integrator}, but KeyCLD's protocol uses "
            f"{integrator}"
        )
    if path is not None:
        _save_atomically(recording, path)
    return recording


def _save_atomically(recording: Recording, path: pathlib.Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.tmp.npz")
    try:
        recording.save(temporary)
        os.replace(temporary, path)
    finally:
        if temporary.exists():
            temporary.unlink()


def keycld_dataset(
    scene: str,
    *,
    runs: int = 500,
    frames: int = 50,
    noise: float = 0.0,
    seed: int = 0,
    cache: "bool | str | os.PathLike" = True,
    progress: bool = False,
) -> Sequences:
    """A KeyCLD dataset as `cldyn.Sequences` of keypoint states relative to the scene's first joint.

    The runs of `keycld_recording` (same arguments), shifted by `keycld_origin(scene)` so that the
    constraints of `cldyn.keycld_constraint(scene)` apply. Split it as the paper does with
    `data.split(450)`.

    !!! example

        ```python
        data = cldyn.mujoco.keycld_dataset("acrobot", seed=0)      # 500 runs x 50 frames, dt 0.01
        train, validation = data.split(450)
        model = cldyn.keycld_model(4, 2, cldyn.keycld_constraint("acrobot"), key=key)
        ```
    """
    recording = keycld_recording(
        scene, runs=runs, frames=frames, noise=noise, seed=seed, cache=cache, progress=progress
    )
    return Sequences.from_recording(recording, origin=keycld_origin(scene))
