"""Helpers shared by the library's modules: atomic file writes, argument checks, optional imports.

One home for what several layers need, so that each is written once.
"""

import importlib
import os
import pathlib
import tempfile
from collections.abc import Callable
from types import ModuleType

import numpy as np

# Which extra of `pip install cldyn[...]` brings each optional import.
_EXTRAS = {
    "mujoco": "mujoco",
    "dm_control": "mujoco",
    "matplotlib": "vision",
    "imageio": "vision",
    "tqdm": "vision",
}


def optional_import(name: str, *, purpose: str) -> ModuleType:
    """Import an optional dependency, or raise an `ImportError` that names the extra to install.

    **Arguments:**

    - `name`: the module, e.g. `"matplotlib.pyplot"`.
    - `purpose`: what needs it, for the message (e.g. `"Identification.save's plots"`).
    """
    try:
        return importlib.import_module(name)
    except ImportError as error:
        top = name.split(".")[0]
        extra = _EXTRAS.get(top)
        hint = f"pip install 'cldyn[{extra}]'" if extra else f"pip install {top}"
        raise ImportError(f"{purpose} needs the optional package {top!r}: {hint}", name=top) from error


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: "str | os.PathLike", data: bytes | str) -> pathlib.Path:
    """Write `data` to `path` so that a reader sees either the old file or the whole new one.

    The data go to a temporary file in the same directory, are flushed to disk (`fsync`) and then
    renamed over `path` (`os.replace`, atomic on POSIX), as `atomic_save` does. The file gets the
    permissions a plain `open(path, "w")` would give (the process's umask), not the private mode of
    temporary files.

    **Returns:** the path written.
    """
    payload = data.encode() if isinstance(data, str) else data
    return atomic_save(path, lambda temporary: temporary.write_bytes(payload))


def atomic_save(path: "str | os.PathLike", write: Callable[[pathlib.Path], object]) -> pathlib.Path:
    """Call `write(temporary_path)` and rename the result over `path` atomically.

    For writers that take a path rather than bytes (`numpy.savez`, matplotlib's `savefig`). The
    temporary file keeps `path`'s suffix, so writers that infer the format from it still work.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(
        prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent
    )
    os.close(handle)
    try:
        write(pathlib.Path(temporary))
        with open(temporary, "rb") as file:
            os.fsync(file.fileno())
        os.chmod(temporary, 0o666 & ~_umask())
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.unlink(temporary)
        raise
    return path


def check_positive(name: str, value, *, integer: bool = False, allow_zero: bool = False):
    """`value` if it is a finite positive number (an integer where `integer`), else a `ValueError`
    that names the argument and what it must be."""
    kind = "integer" if integer else "number"
    bound = ">= 0" if allow_zero else "> 0"
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite {kind} {bound}, got {value!r}") from None
    ok = np.isfinite(number) and (number >= 0 if allow_zero else number > 0)
    if integer and ok:
        ok = number == int(number) and not isinstance(value, bool)
    if not ok:
        raise ValueError(f"{name} must be a finite {kind} {bound}, got {value!r}")
    return int(number) if integer else value


def check_fraction(name: str, value, *, low_open: bool = True, high_open: bool = True) -> float:
    """`value` as a float inside `(0, 1)` (ends included where not open), else a `ValueError` naming it."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number between 0 and 1, got {value!r}") from None
    above = number > 0 if low_open else number >= 0
    below = number < 1 if high_open else number <= 1
    if not (np.isfinite(number) and above and below):
        interval = ("(" if low_open else "[") + "0, 1" + (")" if high_open else "]")
        raise ValueError(f"{name} must lie in {interval}, got {value!r}")
    return number


# The files `cldyn.mujoco.validate` writes, named here (without MuJoCo) so that the command line can
# check its output directory before it needs the [mujoco] extra.
VALIDATION_REPORT = "validation.json"
VALIDATION_PLOT = "keypoint_error.png"
