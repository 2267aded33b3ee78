"""Checkpoints: a PyTree (equinox serialisation, never pickle) and a JSON header in one hashed file.

The file is `CLDYN-CHECKPOINT/2`, the header as one line of JSON, the SHA-256 of header and payload,
then the payload. The checksum covers the header too, so an edited field (the step, the key, the
history) is refused like a flipped bit in the parameters. Files are written atomically
(`cldyn._misc.atomic_write`): a reader, or a crash during the write, sees the old file or the new one.
"""

import hashlib
import io
import json
import os
import pathlib
from collections.abc import Callable
from typing import Any

import equinox as eqx

from ._misc import atomic_write

_MAGIC = b"CLDYN-CHECKPOINT/2\n"
_OLD_MAGIC = b"CLDYN-CHECKPOINT/1\n"


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: missing, corrupt, edited, or made for another model,
    optimiser or training (other data, loss, key or stage)."""


def serialise(tree) -> bytes:
    """The bytes of `eqx.tree_serialise_leaves(tree)`."""
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, tree)
    return buffer.getvalue()


def _digest(header_line: bytes, payload: bytes) -> bytes:
    return hashlib.sha256(header_line + b"\n" + payload).hexdigest().encode()


def save_checkpoint(path: "str | os.PathLike", tree, header: dict) -> pathlib.Path:
    """Write `tree` and a JSON-able `header` to one file, atomically.

    **Arguments:**

    - `path`: the file.
    - `tree`: any PyTree of arrays (e.g. `(model, optimiser state)`), stored with
      `eqx.tree_serialise_leaves`.
    - `header`: a JSON-able dict (e.g. the step, the key, the history); `payload_bytes` is added.

    **Returns:** the path written.
    """
    payload = serialise(tree)
    line = json.dumps(dict(header, payload_bytes=len(payload)), sort_keys=True, allow_nan=False).encode()
    return atomic_write(path, _MAGIC + line + b"\n" + _digest(line, payload) + b"\n" + payload)


def _split(path: pathlib.Path, raw: bytes) -> tuple[bytes, bytes, bytes]:
    if raw.startswith(_OLD_MAGIC):
        raise CheckpointError(
            f"checkpoint {path} has the format CLDYN-CHECKPOINT/1 of an older cldyn, whose header is "
            "not covered by its checksum; start the fit afresh"
        )
    if not raw.startswith(_MAGIC):
        raise CheckpointError(f"checkpoint {path} is corrupt: it does not start with a cldyn header")
    end = raw.find(b"\n", len(_MAGIC))
    stop = raw.find(b"\n", end + 1) if end >= 0 else -1
    if end < 0 or stop < 0:
        raise CheckpointError(f"checkpoint {path} is corrupt: truncated header")
    return raw[len(_MAGIC) : end], raw[end + 1 : stop], raw[stop + 1 :]


def read_header(path: "str | os.PathLike") -> tuple[dict, bytes]:
    """The verified header of a checkpoint and its payload.

    **Returns:** `(header, payload)`. Raises `CheckpointError`, naming the file, when it cannot be
    read, is truncated, or its header or data do not match the checksum.
    """
    path = pathlib.Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise CheckpointError(f"checkpoint {path}: cannot read it ({error})") from error
    line, digest, payload = _split(path, raw)
    if digest != _digest(line, payload):
        raise CheckpointError(
            f"checkpoint {path} is corrupt: its header or data do not match its checksum "
            "(truncated or modified file)"
        )
    try:
        header = json.loads(line)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise CheckpointError(f"checkpoint {path} is corrupt: unreadable header ({error})") from error
    if not isinstance(header, dict) or header.get("payload_bytes") != len(payload):
        raise CheckpointError(f"checkpoint {path} is corrupt: its header does not describe its data")
    return header, payload


def load_checkpoint(
    path: "str | os.PathLike", like, *, check: Callable[[dict], None] | None = None
) -> tuple[Any, dict]:
    """Read a checkpoint written by `save_checkpoint` into the structure of `like`.

    **Arguments:**

    - `path`: the file.
    - `like`: a PyTree of the structure, shapes and dtypes saved (e.g. a fresh model and optimiser
      state).
    - `check`: called with the verified header before the data are read (to refuse a checkpoint of
      another training by what its header says, rather than by a shape that does not fit).

    **Returns:** `(tree, header)`. Raises `CheckpointError`, naming the file, when it is truncated,
    corrupt or edited, or does not match `like`.
    """
    header, payload = read_header(path)
    if check is not None:
        check(header)
    try:
        tree = eqx.tree_deserialise_leaves(io.BytesIO(payload), like)
    except Exception as error:  # equinox/numpy raise several types for a mismatch
        raise CheckpointError(
            f"checkpoint {path} does not match this model and optimiser ({type(error).__name__}: {error})"
        ) from error
    return tree, header
