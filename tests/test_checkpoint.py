"""Checkpoint files: round trip, and every kind of damage refused with the file's name."""

import hashlib

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
from cldyn._checkpoint import load_checkpoint, read_header, save_checkpoint


class _Pair(eqx.Module):
    a: jnp.ndarray
    b: jnp.ndarray


def _tree():
    return _Pair(jnp.arange(6.0).reshape(2, 3), jnp.array([1.5, -2.0]))


def _like():
    return _Pair(jnp.zeros((2, 3)), jnp.zeros(2))


@pytest.fixture
def saved(tmp_path):
    path = tmp_path / "checkpoint.eqx"
    save_checkpoint(path, _tree(), {"step": 40, "history": [{"step": 40, "loss": 0.5}], "seconds": 1.0})
    return path


def test_round_trip_keeps_tree_and_header(saved):
    tree, header = load_checkpoint(saved, _like())
    np.testing.assert_array_equal(tree.a, _tree().a)
    np.testing.assert_array_equal(tree.b, _tree().b)
    assert header["step"] == 40 and header["history"] == [{"step": 40, "loss": 0.5}]
    # the checksum line is the SHA-256 of the header line and the payload
    magic, line, digest, payload = saved.read_bytes().split(b"\n", 3)
    assert magic == b"CLDYN-CHECKPOINT/2"
    assert digest == hashlib.sha256(line + b"\n" + payload).hexdigest().encode()


def _edit(path, old: bytes, new: bytes):
    raw = path.read_bytes()
    assert raw.count(old) == 1
    path.write_bytes(raw.replace(old, new))


@pytest.mark.parametrize(
    "damage",
    [
        lambda p: p.write_bytes(p.read_bytes()[:-3]),  # truncated payload
        lambda p: p.write_bytes(p.read_bytes()[:30]),  # truncated header
        lambda p: _edit(p, b'"step": 40}\n', b'"step": 10}\n'),  # an edited header field, same length
        lambda p: _edit(p, b'"seconds"', b'"secondz"'),  # a renamed key
        lambda p: p.write_bytes(p.read_bytes()[:-1] + bytes([p.read_bytes()[-1] ^ 1])),  # one flipped bit
        lambda p: p.write_bytes(b"garbage"),
    ],
    ids=["truncated", "truncated-header", "edited-step", "renamed-key", "flipped-bit", "garbage"],
)
def test_damage_is_refused_naming_the_file(saved, damage):
    damage(saved)
    with pytest.raises(cldyn.CheckpointError, match=r"checkpoint .*checkpoint\.eqx is corrupt"):
        read_header(saved)


def test_old_format_and_foreign_structure_are_refused(saved, tmp_path):
    with pytest.raises(cldyn.CheckpointError, match=r"does not match this model and optimiser"):
        load_checkpoint(saved, _Pair(jnp.zeros((3, 3)), jnp.zeros(2)))
    old = tmp_path / "old.eqx"
    old.write_bytes(b'CLDYN-CHECKPOINT/1\n{"step": 3}\npayload')
    with pytest.raises(cldyn.CheckpointError, match="older cldyn"):
        load_checkpoint(old, _like())
    with pytest.raises(cldyn.CheckpointError, match="cannot read it"):
        load_checkpoint(tmp_path / "missing.eqx", _like())


def test_check_sees_the_header_before_the_data_are_read(saved):
    def refuse(header):
        raise cldyn.CheckpointError(f"step {header['step']} refused")

    with pytest.raises(cldyn.CheckpointError, match="step 40 refused"):
        load_checkpoint(saved, _Pair(jnp.zeros((3, 3)), jnp.zeros(2)), check=refuse)


def test_writes_are_atomic_and_leave_no_temporary_files(saved):
    save_checkpoint(saved, _tree(), {"step": 41})
    assert read_header(saved)[0]["step"] == 41
    assert sorted(p.name for p in saved.parent.iterdir()) == ["checkpoint.eqx"]
