"""Runs of keypoint states: the one trajectory container for learning and for recorded data.

`Sequences` holds what the losses, `fit` and `evaluate` consume (positions, controls, a sampling
interval, optionally velocities and accelerations) and whatever a producer recorded beside them:
run-leading arrays in `extras` (MuJoCo's joint states and forces, noise-free positions, frames) and
JSON metadata in `info` (names, the scene, the seed). One `.npz` schema, `cldyn.Sequences/2`, stores
all of it.
"""

import json
import os
import pathlib
import types
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any, TypeAlias

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Shaped

from ._custom_types import ArrayInput
from ._misc import atomic_save

SCHEMA = "cldyn.Sequences/2"
_NAME = "Sequences"

# Arrays are kept where they are given: numpy arrays stay on the host (float64 survives without
# JAX's 64-bit mode, and nothing is copied to a device until a jitted function takes them), JAX
# arrays and tracers stay JAX arrays (a `Sequences` built inside a jitted loss).
Data: TypeAlias = Array | np.ndarray


# -- metadata ---------------------------------------------------------------------------------------


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray | jax.Array):
        return np.asarray(value).tolist()
    if isinstance(value, Mapping):
        return dict(value)
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def _freeze(value):
    if isinstance(value, dict):
        return types.MappingProxyType({key: _freeze(item) for key, item in value.items()})
    if isinstance(value, list):
        return tuple(_freeze(item) for item in value)
    return value


class Info(Mapping):
    """Read-only JSON metadata of a `Sequences`: a mapping whose lists read as tuples.

    Held as canonical JSON text, so that it is hashable and two equal metadata compare equal: it is
    static configuration of the `Sequences` module (not a PyTree leaf), and a jitted function of
    the data compiles once per distinct metadata.
    """

    __slots__ = ("_text", "_value")

    def __init__(self, mapping: Mapping[str, Any] | None = None):
        mapping = {} if mapping is None else mapping
        if isinstance(mapping, Info):
            text = mapping._text
        else:
            if not isinstance(mapping, Mapping):
                raise TypeError(
                    f"info must be a mapping of names to JSON values, got {type(mapping).__name__}"
                )
            bad = [key for key in mapping if not isinstance(key, str)]
            if bad:
                raise TypeError(f"info keys must be strings, got {bad}")
            try:
                text = json.dumps(
                    dict(mapping), sort_keys=True, allow_nan=False, default=_json_default,
                    separators=(",", ":"),
                )
            except (TypeError, ValueError) as error:
                raise ValueError(
                    f"info must hold finite JSON values (numbers, strings, lists): {error}"
                ) from None
        object.__setattr__(self, "_text", text)
        object.__setattr__(self, "_value", _freeze(json.loads(text)))

    def __setattr__(self, name, value):
        raise AttributeError("Info is read-only; build a new Sequences with dataclasses.replace")

    @property
    def text(self) -> str:
        """The canonical JSON text."""
        return self._text

    def __getitem__(self, key: str):
        return self._value[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._value)

    def __len__(self) -> int:
        return len(self._value)

    def __hash__(self) -> int:
        return hash(self._text)

    def __eq__(self, other) -> bool:
        if isinstance(other, Info):
            return self._text == other._text
        if isinstance(other, Mapping):
            try:
                return self._text == Info(other)._text
            except (TypeError, ValueError):
                return False
        return NotImplemented

    def __repr__(self) -> str:
        shown = {key: (f"<{len(v)} characters>" if isinstance(v, str) and len(v) > 80 else v)
                 for key, v in self._value.items()}
        return f"Info({shown})"


# -- arrays -----------------------------------------------------------------------------------------


def _first_bad(array: np.ndarray) -> tuple[int, ...] | None:
    bad = np.argwhere(~np.isfinite(array))
    return None if bad.size == 0 else tuple(int(i) for i in bad[0])


def _as_float(value) -> Data:
    if isinstance(value, jax.Array):
        return value if jnp.issubdtype(value.dtype, jnp.inexact) else value.astype(float)
    array = np.asarray(value)
    if array.dtype == object:
        raise TypeError("arrays of Python objects are not data")
    return array if np.issubdtype(array.dtype, np.inexact) else array.astype(np.float64)


def _as_array(value) -> Data:
    if isinstance(value, jax.Array):
        return value
    array = np.asarray(value)
    if array.dtype == object:
        raise TypeError("arrays of Python objects are not data")
    return array


def _is_concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def _check_finite(name: str, value) -> None:
    if value is None or not _is_concrete(value) or not np.issubdtype(np.asarray(value).dtype, np.inexact):
        return
    array = np.asarray(value)
    bad = _first_bad(array)
    if bad is not None:
        raise ValueError(
            f"Sequences: {name} contains a NaN or infinite value at (run, sample, ...) = {bad}: {array[bad]}"
        )


def _cast(dtype) -> Callable:
    def cast(a):
        return a.astype(dtype) if np.issubdtype(a.dtype, np.inexact) else a

    return cast


class Sequences(eqx.Module):
    """Runs of keypoint states sampled at a constant interval, with their controls.

    What the losses, `fit` and `evaluate` consume, and what `cldyn.mujoco.record` produces. All runs
    share the number of samples `T`; a batch of runs is again a `Sequences` (a PyTree whose arrays
    all lead with the run axis; `dt` and `info` are static).

    **Arguments:**

    - `x`: keypoint positions, shape `(runs, T, k)`.
    - `u`: controls, shape `(runs, T, l)` (the control applied from each sample to the next),
      `(runs, l)` (constant per run, as in KeyCLD's data), or `None` for none (`l = 0`).
    - `dt`: the sampling interval `h` in seconds.
    - `xd`, `xdd`: known velocities and accelerations, shape `(runs, T, k)`, or `None`. Only
      `InverseDynamics` needs them; the other losses estimate derivatives by central differences.
    - `extras`: other arrays recorded with the runs, by name, each leading with the run axis
      (`record` stores `qpos`, `qvel`, `qacc`, `x_clean`, `qfrc_passive`, `qfrc_actuator`,
      `qfrc_constraint`, `qfrc_bias`). `take`, `split` and `astype` act on them too.
    - `info`: JSON metadata (names, the scene, the seed, ...), read back as a read-only mapping
      (`Info`) whose lists are tuples.

    Arrays are kept as given: numpy arrays stay numpy (float64 is kept without JAX's 64-bit mode),
    JAX arrays stay JAX arrays; integer positions and controls become floating. Concrete inputs are
    checked: shapes that disagree or NaN/infinite values raise a `ValueError` that names the array
    and the first offending index.

    !!! example

        ```python
        data = cldyn.Sequences(x, u, dt=0.02)         # x: (500, 50, 2), u: (500, 1)
        train, validation = data.split(450)           # KeyCLD A.6: the last 50 runs validate
        data.save("pendulum.npz")
        ```
    """

    x: Float[Data, "runs T k"]
    u: Float[Data, "runs T l"]
    dt: float = eqx.field(static=True)
    xd: Float[Data, "runs T k"] | None
    xdd: Float[Data, "runs T k"] | None
    extras: dict[str, Shaped[Data, "runs ..."]]
    info: Info = eqx.field(static=True)

    def __init__(
        self,
        x: ArrayInput,
        u: ArrayInput | None = None,
        dt: float = 1.0,
        *,
        xd: ArrayInput | None = None,
        xdd: ArrayInput | None = None,
        extras: Mapping[str, ArrayInput] | None = None,
        info: Mapping[str, Any] | None = None,
    ):
        x = _as_float(x)
        if x.ndim != 3:
            raise ValueError(f"Sequences: x must have shape (runs, T, k), got {x.shape}")
        runs, samples, _ = x.shape
        if u is None:
            u = np.zeros((runs, samples, 0), dtype=x.dtype)
        u = _as_float(u)
        if u.ndim == 2:
            if u.shape[0] != runs:
                raise ValueError(f"Sequences: u has {u.shape[0]} runs but x has {runs}")
            broadcast = jnp.broadcast_to if isinstance(u, jax.Array) else np.broadcast_to
            u = broadcast(u[:, None, :], (runs, samples, u.shape[1]))
        if u.ndim != 3 or u.shape[:2] != (runs, samples):
            raise ValueError(
                f"Sequences: u must have shape ({runs}, {samples}, l) or ({runs}, l) to match x "
                f"{x.shape}, got {u.shape}"
            )
        try:
            dt = float(dt)
        except (TypeError, ValueError):
            raise ValueError(f"Sequences: dt must be a positive time step, got {dt!r}") from None
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"Sequences: dt must be a positive time step, got {dt}")
        derivatives = {}
        for name, value in (("xd", xd), ("xdd", xdd)):
            if value is not None:
                value = _as_float(value)
                if value.shape != x.shape:
                    raise ValueError(
                        f"Sequences: {name} must have the shape of x {x.shape}, got {value.shape}"
                    )
            derivatives[name] = value
        arrays = {}
        for name, value in ({} if extras is None else dict(extras)).items():
            if not isinstance(name, str) or not name or "/" in name:
                raise ValueError(
                    f"Sequences: extras names must be non-empty strings without '/', got {name!r}"
                )
            value = _as_array(value)
            if value.ndim < 1 or value.shape[0] != runs:
                raise ValueError(
                    f"Sequences: extras[{name!r}] must lead with the run axis ({runs}, ...), "
                    f"got {value.shape}"
                )
            arrays[name] = value
        for name, value in (("x", x), ("u", u), *derivatives.items(),
                            *((f"extras[{key!r}]", value) for key, value in arrays.items())):
            _check_finite(name, value)
        self.x = x
        self.u = u
        self.dt = dt
        self.xd = derivatives["xd"]
        self.xdd = derivatives["xdd"]
        self.extras = arrays
        self.info = Info(info)

    @property
    def num_runs(self) -> int:
        """The number of runs."""
        return self.x.shape[0]

    @property
    def num_samples(self) -> int:
        """The number `T` of samples per run."""
        return self.x.shape[1]

    @property
    def size(self) -> int:
        """The number `k` of keypoint coordinates."""
        return self.x.shape[2]

    @property
    def num_inputs(self) -> int:
        """The number `l` of controls."""
        return self.u.shape[2]

    @property
    def ts(self) -> np.ndarray:
        """The sample times from 0, `dt * arange(T)`, shape `(T,)` (numpy, so concrete under jit)."""
        return np.arange(self.num_samples) * self.dt

    def take(self, runs) -> "Sequences":
        """The runs at the given indices (an integer array or a slice), extras included; works under
        `jax.jit`."""
        return jax.tree.map(lambda a: a[runs], self)

    def split(self, first: int | float) -> tuple["Sequences", "Sequences"]:
        """Split the runs in two, in order: the first `first` runs (or that fraction) and the rest.

        KeyCLD (appendix A.6) trains on the first 450 of 500 runs and validates on the last 50.
        """
        count = int(round(first * self.num_runs)) if isinstance(first, float) else int(first)
        if not 0 < count < self.num_runs:
            raise ValueError(f"split: need 0 < first < {self.num_runs} runs, got {first}")
        return self.take(slice(0, count)), self.take(slice(count, None))

    def astype(self, dtype) -> "Sequences":
        """The same data with every floating array (extras included) cast to `dtype`; integer
        extras (e.g. frames) are left as they are."""
        return jax.tree.map(_cast(dtype), self)

    def relative_to(self, origin: ArrayInput) -> "Sequences":
        """The same runs with the keypoint positions relative to a point.

        `origin` (shape `(d,)`, e.g. the pivot, so that KeyCLD's `Anchor` constraints at the origin
        apply) is subtracted from every keypoint of `x` and of `extras["x_clean"]` (the noise-free
        positions `record` stores) where present; velocities, accelerations and the other extras
        are unchanged. `info["origin"]` records the total shift.
        """
        origin = np.asarray(origin, dtype=float).reshape(-1)
        d = origin.shape[0]
        if d == 0 or self.size % d:
            raise ValueError(f"origin has {d} coordinates; keypoints of size {self.size} do not split")
        shift = np.tile(origin, self.size // d)
        extras = dict(self.extras)
        if "x_clean" in extras:
            extras["x_clean"] = extras["x_clean"] - shift.astype(extras["x_clean"].dtype)
        before = np.asarray(self.info.get("origin", np.zeros(d)), dtype=float)
        info = {**self.info, "origin": (before + origin).tolist()}
        x = self.x - shift.astype(self.x.dtype)
        return Sequences(x, self.u, self.dt, xd=self.xd, xdd=self.xdd, extras=extras, info=info)

    # -- files --------------------------------------------------------------------------------------

    def save(self, path: "str | os.PathLike", *, overwrite: bool = False) -> pathlib.Path:
        """Save to a compressed `.npz` file of schema `cldyn.Sequences/2`, atomically.

        **Arguments:**

        - `path`: the file; `.npz` is appended if missing.
        - `overwrite`: replace an existing file; otherwise an existing file raises a
          `FileExistsError` naming it and is left untouched.

        **Returns:** the path written.

        The file holds the arrays `x`, `u`, `xd` and `xdd` (where present), `extras/<name>` for each
        extra, and `metadata`, a JSON text with the schema, `dt`, the shape, the list of arrays and
        `info`. It is written to a temporary file and renamed over `path`, so a reader (or a crash)
        never sees half a file. No entry is a pickle.
        """
        path = pathlib.Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        if not overwrite and (path.exists() or path.is_symlink()):
            raise FileExistsError(f"{path}: already exists; pass overwrite=True to replace it")
        if path.is_dir():
            raise IsADirectoryError(f"{path}: is a directory")
        if not all(_is_concrete(a) for a in jax.tree.leaves(self)):
            raise TypeError("Sequences.save needs concrete arrays (not inside jax.jit)")
        arrays = {"x": np.asarray(self.x), "u": np.asarray(self.u)}
        for name in ("xd", "xdd"):
            if getattr(self, name) is not None:
                arrays[name] = np.asarray(getattr(self, name))
        for name, value in self.extras.items():
            arrays[f"extras/{name}"] = np.asarray(value)
        metadata = {
            "schema": SCHEMA,
            "dt": self.dt,
            "runs": self.num_runs,
            "samples": self.num_samples,
            "arrays": {name: [list(a.shape), a.dtype.str] for name, a in arrays.items()},
            "info": json.loads(self.info.text),
        }
        text = json.dumps(metadata, allow_nan=False)
        return atomic_save(
            path, lambda temporary: np.savez_compressed(temporary, metadata=np.array(text), **arrays)
        )

    @classmethod
    def load(cls, path: "str | os.PathLike") -> "Sequences":
        """Load a file written by `save` (schema `cldyn.Sequences/2`, or the older `cldyn.Sequences/1`
        and `cldyn.mujoco.Recording/1`, told apart by the schema they name).

        **Arguments:**

        - `path`: the `.npz` file.

        **Returns:** the `Sequences`, with numpy arrays of the dtypes saved (bit for bit).

        A missing file raises `FileNotFoundError`; a file that is not a readable `.npz` (corrupt,
        truncated, a pickle), names no known schema, lacks an array, or whose arrays disagree with
        their metadata or with each other raises a `ValueError` that names the file and the problem.
        Pickled entries are never loaded.
        """
        path = pathlib.Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file")
        if not path.is_file():
            raise ValueError(f"{path}: not a file")
        contents = _read_npz(path)
        if "metadata" not in contents:
            raise ValueError(f"{path}: not a cldyn data file (no metadata entry)")
        try:
            metadata = json.loads(str(contents.pop("metadata")))
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise ValueError(f"{path}: corrupt metadata ({error})") from None
        if not isinstance(metadata, dict):
            raise ValueError(f"{path}: corrupt metadata (not a JSON object)")
        schema = metadata.get("schema")
        reader = _READERS.get(schema)
        if reader is None:
            raise ValueError(
                f"{path}: schema {schema!r} is not one this version reads ({', '.join(sorted(_READERS))})"
            )
        try:
            return reader(cls, contents, metadata)
        except _Problem as error:
            raise ValueError(f"{path}: {error}") from None
        except (ValueError, TypeError) as error:
            raise ValueError(f"{path}: {error}") from None


class _Problem(Exception):
    """What is wrong with a file's contents, without the file's name (added by `load`)."""


def _read_npz(path: pathlib.Path) -> dict[str, np.ndarray]:
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path}: not an .npz file (no zip archive: empty, truncated or another format)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            contents = {}
            for name in npz.files:
                try:
                    contents[name] = npz[name]
                except ValueError as error:
                    # numpy refuses object arrays with advice to allow pickles; never follow it
                    if "pickle" in str(error):
                        raise ValueError(
                            f"{path}: entry {name!r} holds pickled Python objects; cldyn data files hold "
                            "plain arrays only, and pickles are never loaded (they can run code)"
                        ) from None
                    raise ValueError(f"{path}: entry {name!r} is corrupt ({error})") from None
    except ValueError:
        raise
    except (OSError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as error:
        raise ValueError(f"{path}: not a readable .npz file, corrupt or truncated ({error})") from None
    return contents


def _number(metadata: dict, key: str, kind=float):
    if key not in metadata:
        raise _Problem(f"metadata lacks {key!r}")
    value = metadata[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _Problem(f"metadata {key!r} is not a number: {value!r}")
    return kind(value)


def _read_v2(cls, contents: dict, metadata: dict) -> Sequences:
    listed = metadata.get("arrays")
    if not isinstance(listed, dict):
        raise _Problem("metadata lacks the list of arrays")
    missing = sorted(set(listed) - set(contents))
    unlisted = sorted(set(contents) - set(listed))
    if missing:
        raise _Problem(f"missing arrays {missing}")
    if unlisted:
        raise _Problem(f"arrays {unlisted} are not listed in the metadata")
    for name, described in listed.items():
        try:
            shape, dtype = tuple(described[0]), np.dtype(described[1])
        except (TypeError, ValueError, IndexError) as error:
            raise _Problem(f"metadata of array {name!r} is corrupt ({error})") from None
        if contents[name].shape != shape or contents[name].dtype != dtype:
            raise _Problem(
                f"array {name!r} has shape {contents[name].shape} and dtype {contents[name].dtype}, "
                f"the metadata says {shape} and {dtype}"
            )
    for name in ("x", "u"):
        if name not in contents:
            raise _Problem(f"missing array {name!r}")
    dt = _number(metadata, "dt")
    runs, samples = _number(metadata, "runs", int), _number(metadata, "samples", int)
    if contents["x"].shape[:2] != (runs, samples):
        raise _Problem(
            f"x has shape {contents['x'].shape}, the metadata says {runs} runs of {samples} samples"
        )
    info = metadata.get("info", {})
    if not isinstance(info, dict):
        raise _Problem("metadata 'info' is not a JSON object")
    extras = {name.removeprefix("extras/"): a for name, a in contents.items() if name.startswith("extras/")}
    return cls(
        contents["x"], contents["u"], dt, xd=contents.get("xd"), xdd=contents.get("xdd"),
        extras=extras, info=info,
    )


def _read_v1(cls, contents: dict, metadata: dict) -> Sequences:
    for name in ("x", "u"):
        if name not in contents:
            raise _Problem(f"missing array {name!r}")
    dt = _number(metadata, "dt")
    return cls(contents["x"], contents["u"], dt, xd=contents.get("xd"), xdd=contents.get("xdd"))


_RECORDING_EXTRAS = (
    "qpos", "qvel", "qacc", "x_clean", "qfrc_passive", "qfrc_actuator", "qfrc_constraint", "qfrc_bias",
)
_RECORDING_INFO = (
    "keypoint_names", "joint_names", "actuator_names", "mjcf", "mjcf_xml", "physics_dt", "integrator",
    "noise", "seed",
)


def _read_recording_v1(cls, contents: dict, metadata: dict) -> Sequences:
    """`cldyn.mujoco.Recording/1` files, as `record` wrote them before they became `Sequences`."""
    needed = ("time", "x", "xd", "xdd", "u", "basis", *_RECORDING_EXTRAS)
    missing = [name for name in needed if name not in contents]
    if missing:
        raise _Problem(f"missing arrays {missing}")
    absent = [key for key in _RECORDING_INFO if key not in metadata]
    if absent:
        raise _Problem(f"metadata lacks {absent}")
    dt = _number(metadata, "dt")
    time = contents["time"]
    if contents["x"].ndim != 3 or time.shape != (contents["x"].shape[1],):
        raise _Problem(f"time has shape {time.shape}, x {contents['x'].shape}")
    if not np.allclose(time, dt * np.arange(time.shape[0]), rtol=1e-9, atol=1e-12 * dt):
        raise _Problem(f"the times are not multiples of the metadata's dt = {dt}")
    basis = np.asarray(contents["basis"], dtype=float).reshape(-1, 3)
    info = {key: metadata[key] for key in _RECORDING_INFO}
    info["basis"] = basis.tolist()
    info["keypoint_dim"] = 2 if basis.shape[0] == 2 else 3
    data = cls(
        contents["x"], contents["u"], dt, xd=contents["xd"], xdd=contents["xdd"],
        extras={name: contents[name] for name in _RECORDING_EXTRAS}, info=info,
    )
    k = info["keypoint_dim"] * len(info["keypoint_names"])
    if data.size != k or data.num_inputs != len(info["actuator_names"]):
        raise _Problem(
            f"x has {data.size} coordinates and u {data.num_inputs} controls, the names say {k} and "
            f"{len(info['actuator_names'])}"
        )
    return data


_READERS: dict[str, Callable[..., Sequences]] = {
    SCHEMA: _read_v2,
    "cldyn.Sequences/1": _read_v1,
    "cldyn.mujoco.Recording/1": _read_recording_v1,
}


def central_difference(x: Float[Array, "*batch T k"], dt: float) -> Float[Array, "*batch T-2 k"]:
    """The central difference $(x_{i+1} - x_{i-1}) / 2h$ along the time axis (eq. 11, 12).

    **Arguments:**

    - `x`: samples along the second-to-last axis, shape `(..., T, k)`.
    - `dt`: the interval `h`.

    **Returns:** the derivative at samples `1 .. T-2`, shape `(..., T-2, k)`.

    !!! example

        ```python
        xd = cldyn.central_difference(data.x, data.dt)     # (runs, T - 2, k)
        ```
    """
    return (x[..., 2:, :] - x[..., :-2, :]) / (2 * dt)
