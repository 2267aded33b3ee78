"""The frames container: rendered image sequences with their ground truth, saved as one `.npz` schema,
and the cache that keeps rendered datasets between sessions."""

import dataclasses
import hashlib
import json
import os
import pathlib
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, Shaped, UInt8

from cldyn._data import _read_npz as read_npz
from cldyn._misc import atomic_save

SCHEMA = "keyvision.Frames/1"
_CACHE_ENV = "KEYVISION_CACHE"


def cache_directory() -> pathlib.Path:
    """Where `keyvision.render` caches datasets: `$KEYVISION_CACHE`, or else `~/.cache/keyvision`.

    !!! example

        ```python
        os.environ["KEYVISION_CACHE"] = "/scratch/keyvision"
        keyvision.cache_directory()   # PosixPath('/scratch/keyvision')
        ```
    """
    root = os.environ.get(_CACHE_ENV)
    return pathlib.Path(root) if root else pathlib.Path.home() / ".cache" / "keyvision"


def cache_key(request: Mapping[str, Any]) -> str:
    """The SHA-256 of a JSON-able description of what was rendered (scene XML, camera, protocol,
    seed, ...): the name under which the frames are cached."""
    text = json.dumps(request, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


@dataclasses.dataclass(frozen=True, eq=False)
class PlanarCamera:
    """How a fixed camera sees the plane of motion: a projective map between the image frame
    (x right, y up, `[-1, 1]`, origin at the image centre; see `keyvision.pixel_grid`) and planar
    coordinates in metres.

    Planar coordinates are those of cldyn: a world point `p` in the plane has coordinates
    `basis @ p`, with `basis`'s rows the in-plane unit vectors (the second one pointing up, against
    gravity).

    **Fields:**

    - `homography`: `(3, 3)`; the image point `(u, v)` lies over the plane point `(X/W, Y/W)` where
      `(X, Y, W) = homography @ (u, v, 1)`. For a camera that faces the plane squarely this is an
      affine map (its last row is `(0, 0, 1)` up to scale).
    - `basis`: `(2, 3)`, the plane's in-plane unit vectors in world coordinates.

    !!! example

        ```python
        frames = keyvision.render("keycld/pendulum")
        metres = frames.camera.to_plane(keypoints)     # (..., 2) image frame -> plane, metres
        ```
    """

    homography: Float[np.ndarray, "3 3"]
    basis: Float[np.ndarray, "2 3"]

    def __post_init__(self):
        homography = np.asarray(self.homography, dtype=float)
        basis = np.asarray(self.basis, dtype=float)
        if homography.shape != (3, 3) or basis.shape != (2, 3):
            raise ValueError(
                f"PlanarCamera: homography must be (3, 3) and basis (2, 3), got {homography.shape} "
                f"and {basis.shape}"
            )
        object.__setattr__(self, "homography", homography)
        object.__setattr__(self, "basis", basis)

    @staticmethod
    def _apply(matrix: np.ndarray, points) -> np.ndarray:
        points = np.asarray(points, dtype=float)
        homogeneous = points @ matrix[:, :2].T + matrix[:, 2]
        return homogeneous[..., :2] / homogeneous[..., 2:]

    def to_plane(self, points: Float[np.ndarray, "*batch 2"]) -> Float[np.ndarray, "*batch 2"]:
        """Planar coordinates in metres of image-frame points `(..., 2)`."""
        return self._apply(self.homography, points)

    def to_image(self, points: Float[np.ndarray, "*batch 2"]) -> Float[np.ndarray, "*batch 2"]:
        """Image-frame coordinates of planar points in metres `(..., 2)`."""
        return self._apply(np.linalg.inv(self.homography), points)


@dataclasses.dataclass(frozen=True, eq=False)
class Frames:
    """Rendered image sequences, batch-first: `R` runs of `T` frames, with what produced them.

    The ground truth (`extras`) is for diagnostics and evaluation, never for training.

    **Fields:**

    - `frames`: `(R, T, H, W, 3)` uint8 RGB images; row 0 is the top of the image.
    - `u`: `(R, T, l)` the controls (MuJoCo's `ctrl`) held from each frame to the next.
    - `dt`: the time between frames in seconds.
    - `extras`: run-leading ground-truth arrays: `qpos` `(R, T, nq)` and `qvel` `(R, T, nv)` (MuJoCo's
      joint state at each frame) and `keypoints` `(R, T, 2K)` (the scene's keypoints in planar
      coordinates, metres, laid out `[x1, y1, x2, y2, ...]`; names in `info["keypoint_names"]`).
    - `camera`: the `PlanarCamera` map between the image frame and the plane of motion.
    - `info`: JSON-able metadata: `scene`, `mjcf_xml`, `camera`, `protocol`, `seed`,
      `keypoint_names`, `joint_names`, `joint_types`, `actuator_names`, `timestep`, `integrator`,
      `validation_runs`, `mujoco`, `cache_key`.

    !!! example

        ```python
        frames = keyvision.render("keycld/pendulum", seed=0)
        train, validation = frames.split()        # 450 and 50 runs
        images = train.images()                   # float32 in [0, 1]
        ```
    """

    frames: UInt8[np.ndarray, "R T H W 3"]
    u: Float[np.ndarray, "R T l"]
    dt: float
    extras: Mapping[str, np.ndarray]
    camera: PlanarCamera
    info: Mapping[str, Any]

    def __post_init__(self):
        self.check()

    @property
    def num_runs(self) -> int:
        """The number `R` of runs."""
        return self.frames.shape[0]

    @property
    def num_frames(self) -> int:
        """The number `T` of frames per run."""
        return self.frames.shape[1]

    @property
    def image_size(self) -> tuple[int, int]:
        """`(H, W)` in pixels."""
        return self.frames.shape[2], self.frames.shape[3]

    @property
    def ts(self) -> np.ndarray:
        """The frame times `dt * arange(T)`."""
        return self.dt * np.arange(self.num_frames)

    def images(self, dtype=np.float32) -> np.ndarray:
        """The frames as floating-point images in `[0, 1]`, shape `(R, T, H, W, 3)`."""
        return self.frames.astype(dtype) / 255

    def select(self, runs) -> "Frames":
        """The runs picked by `runs` (an index array, a slice or a boolean mask), with the same info."""
        return dataclasses.replace(
            self,
            frames=self.frames[runs],
            u=self.u[runs],
            extras={name: value[runs] for name, value in self.extras.items()},
        )

    def split(self, validation_runs: int | None = None) -> tuple["Frames", "Frames"]:
        """`(train, validation)`: the last `validation_runs` runs validate (`info["validation_runs"]`,
        50 in the paper's protocol, by default)."""
        count = self.info.get("validation_runs", 0) if validation_runs is None else validation_runs
        if not 0 <= count <= self.num_runs:
            raise ValueError(f"validation_runs must lie in [0, {self.num_runs}], got {count}")
        cut = self.num_runs - count
        return self.select(slice(0, cut)), self.select(slice(cut, self.num_runs))

    def check(self, *, where: str = "Frames") -> None:
        """Raise a `ValueError` naming the problem if the arrays disagree in shape or type."""
        frames = self.frames
        if not isinstance(frames, np.ndarray) or frames.dtype != np.uint8 or frames.ndim != 5:
            raise ValueError(
                f"{where}: frames must be a uint8 array (R, T, H, W, 3), got {_describe(frames)}"
            )
        if frames.shape[-1] != 3:
            raise ValueError(f"{where}: frames must have 3 colour channels, got shape {frames.shape}")
        runs, samples = frames.shape[:2]
        if self.u.ndim != 3 or self.u.shape[:2] != (runs, samples):
            raise ValueError(f"{where}: u must have shape ({runs}, {samples}, l), got {self.u.shape}")
        for name, value in self.extras.items():
            if value.shape[:2] != (runs, samples):
                raise ValueError(
                    f"{where}: extras[{name!r}] must lead with ({runs}, {samples}), got {value.shape}"
                )
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"{where}: dt must be a positive number, got {self.dt}")

    def save(self, path: "str | os.PathLike") -> pathlib.Path:
        """Save to a compressed `.npz` file (schema `keyvision.Frames/1`, no pickled objects),
        atomically.

        **Arguments:**

        - `path`: the file; `.npz` is appended if missing.

        **Returns:** the path written.
        """
        path = pathlib.Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        metadata = {"schema": SCHEMA, "dt": self.dt, "extras": sorted(self.extras), "info": dict(self.info)}
        arrays = {
            "frames": self.frames,
            "u": self.u,
            "camera_homography": self.camera.homography,
            "camera_basis": self.camera.basis,
            "metadata": np.array(json.dumps(metadata)),
            **{f"extras.{name}": value for name, value in self.extras.items()},
        }
        return atomic_save(path, lambda temporary: np.savez_compressed(temporary, **arrays))

    @classmethod
    def load(cls, path: "str | os.PathLike") -> "Frames":
        """Load frames saved by `save`.

        **Arguments:**

        - `path`: the `.npz` file.

        **Returns:** the `Frames`. A missing, truncated, corrupt or foreign file raises an error that
        names the file and the problem.
        """
        path = pathlib.Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such frames file")
        contents = read_npz(path)  # cldyn's reader: names the file, never advises loading pickles
        if "metadata" not in contents:
            raise ValueError(f"{path}: not a keyvision frames file (no metadata entry)")
        try:
            metadata = json.loads(str(contents["metadata"]))
        except json.JSONDecodeError as error:
            raise ValueError(f"{path}: corrupt metadata ({error})") from error
        if not isinstance(metadata, dict) or metadata.get("schema") != SCHEMA:
            found = metadata.get("schema") if isinstance(metadata, dict) else None
            raise ValueError(f"{path}: schema {found!r}, expected {SCHEMA!r}")
        try:
            names = [f"extras.{name}" for name in metadata["extras"]]
            missing = [
                n for n in ("frames", "u", "camera_homography", "camera_basis", *names) if n not in contents
            ]
            if missing:
                raise ValueError(f"{path}: missing arrays {missing}")
            return cls(
                frames=contents["frames"],
                u=contents["u"],
                dt=float(metadata["dt"]),
                extras={name: contents[f"extras.{name}"] for name in metadata["extras"]},
                camera=PlanarCamera(contents["camera_homography"], contents["camera_basis"]),
                info=metadata["info"],
            )
        except KeyError as error:
            raise ValueError(f"{path}: metadata lacks {error}") from error
        except ValueError as error:
            if str(error).startswith(str(path)):
                raise
            raise ValueError(f"{path}: {error}") from error


def _describe(value) -> str:
    if isinstance(value, np.ndarray):
        return f"{value.dtype} array of shape {value.shape}"
    return type(value).__name__


class ImageSequences(eqx.Module):
    """Runs of images with their controls: the training data of a `keyvision.KeyCLD` model, the
    counterpart of `cldyn.Sequences` for frames.

    A PyTree whose arrays lead with the run axis, so `cldyn.fit` draws batches from it with
    `cldyn.Runs` or `cldyn.Windows` (a window of frames is again an `ImageSequences`). Frames may stay
    `uint8`: `fit` casts only floating arrays, and the losses convert each batch to floats in `[0, 1]`
    (`images`), so a large dataset costs a quarter of the memory.

    **Arguments:**

    - `frames`: `(runs, T, H, W, C)` images, `uint8` (0..255) or floating (in `[0, 1]`).
    - `u`: `(runs, T, l)` controls held from each frame to the next, `(runs, l)` (one per run), or
      `None` for none.
    - `dt`: the time between frames in seconds.
    - `transforms`: `(runs, T)` integer indices of the dihedral transform under which the estimator
      sees each frame (`keyvision.Augment` draws them for a batch), or `None`: every frame as it is.

    !!! example

        ```python
        train, validation = keyvision.render("keycld/pendulum").split()
        data = keyvision.ImageSequences.from_frames(train)
        ```
    """

    frames: Shaped[Array | np.ndarray, "runs T H W C"]
    u: Float[Array | np.ndarray, "runs T l"]
    dt: float = eqx.field(static=True)
    transforms: Int[Array | np.ndarray, "runs T"] | None = None

    def __init__(self, frames, u=None, dt: float = 1.0, transforms=None):
        frames = frames if isinstance(frames, jax.Array) else np.asarray(frames)
        if frames.ndim != 5:
            raise ValueError(f"ImageSequences: frames must have shape (runs, T, H, W, C), got {frames.shape}")
        runs, samples = frames.shape[:2]
        if u is None:
            u = np.zeros((runs, samples, 0), np.float32)
        if not isinstance(u, jax.Array):
            u = np.asarray(u)
            u = u if np.issubdtype(u.dtype, np.floating) else u.astype(np.float32)
        if u.ndim == 2 and u.shape[0] == runs:
            broadcast = jnp.broadcast_to if isinstance(u, jax.Array) else np.broadcast_to
            u = broadcast(u[:, None, :], (runs, samples, u.shape[1]))
        if u.ndim != 3 or u.shape[:2] != (runs, samples):
            raise ValueError(
                f"ImageSequences: u must have shape ({runs}, {samples}, l) or ({runs}, l), got {u.shape}"
            )
        dt = float(dt)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"ImageSequences: dt must be a positive number, got {dt}")
        if transforms is not None and jnp.shape(transforms) != (runs, samples):
            raise ValueError(
                f"ImageSequences: transforms must have shape ({runs}, {samples}), got {jnp.shape(transforms)}"
            )
        self.frames = frames
        self.u = u
        self.dt = dt
        self.transforms = transforms

    @classmethod
    def from_frames(cls, frames: Frames) -> "ImageSequences":
        """The frames and controls of rendered `Frames` (their ground truth is left behind)."""
        return cls(frames.frames, frames.u.astype(np.float32), frames.dt)

    @property
    def num_runs(self) -> int:
        """The number of runs."""
        return self.frames.shape[0]

    @property
    def num_samples(self) -> int:
        """The number `T` of frames per run."""
        return self.frames.shape[1]

    @property
    def num_inputs(self) -> int:
        """The number `l` of controls."""
        return self.u.shape[2]

    def images(self, dtype=jnp.float32) -> Float[Array, "runs T H W C"]:
        """The frames as a JAX array of `dtype` with values in `[0, 1]` (`uint8` frames are divided
        by 255)."""
        return as_images(self.frames, dtype)


def as_images(frames, dtype=jnp.float32) -> Float[Array, "*batch H W C"]:
    """Frames as floating images in `[0, 1]`: integer frames (0..255) are divided by 255."""
    frames = jnp.asarray(frames)
    if jnp.issubdtype(frames.dtype, jnp.integer):
        return frames.astype(dtype) / 255
    return frames.astype(dtype)
