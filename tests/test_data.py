"""`Sequences`: the one trajectory container (shapes, extras, metadata) and its `.npz` file."""

import dataclasses
import json
import os
import pickle

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn

RUNS, SAMPLES, K, L = 4, 5, 4, 2
DT = 0.02


def _data(**overrides) -> cldyn.Sequences:
    rng = np.random.default_rng(0)
    arguments = dict(
        x=rng.standard_normal((RUNS, SAMPLES, K)),
        u=rng.standard_normal((RUNS, SAMPLES, L)).astype(np.float32),
        dt=DT,
        xd=rng.standard_normal((RUNS, SAMPLES, K)),
        xdd=None,
        extras={
            "qpos": rng.standard_normal((RUNS, SAMPLES, 2)),
            "frames": rng.integers(0, 256, (RUNS, SAMPLES, 3, 3, 3), dtype=np.uint8),
            "label": np.arange(RUNS),
        },
        info={"joint_names": ["a", "b"], "seed": 3, "noise": 0.01, "basis": [[1.0, 0, 0], [0, 0, 1.0]]},
    )
    arguments.update(overrides)
    x, u, dt = arguments.pop("x"), arguments.pop("u"), arguments.pop("dt")
    return cldyn.Sequences(x, u, dt, **arguments)


def _same(a: cldyn.Sequences, b: cldyn.Sequences) -> None:
    """Bit for bit: values, dtypes, which arrays exist, dt and info."""
    assert a.dt == b.dt and a.info == b.info and sorted(a.extras) == sorted(b.extras)
    for name in ("x", "u", "xd", "xdd"):
        first, second = getattr(a, name), getattr(b, name)
        assert (first is None) == (second is None), name
        if first is not None:
            assert np.asarray(first).dtype == np.asarray(second).dtype, name
            np.testing.assert_array_equal(first, second)
    for name, value in a.extras.items():
        assert np.asarray(value).dtype == np.asarray(b.extras[name]).dtype, name
        np.testing.assert_array_equal(value, b.extras[name])


# -- the container ----------------------------------------------------------------------------------


def test_shapes_properties_and_sample_times():
    data = _data()
    assert (data.num_runs, data.num_samples, data.size, data.num_inputs) == (RUNS, SAMPLES, K, L)
    np.testing.assert_array_equal(data.ts, [0.0, 0.02, 0.04, 0.06, 0.08])
    # arrays stay where they were given: numpy float64 and float32 as such
    assert isinstance(data.x, np.ndarray) and data.x.dtype == np.float64 and data.u.dtype == np.float32
    # a control per run is held over the run; none at all is l = 0
    per_run = cldyn.Sequences(np.zeros((2, 3, 2)), [[1.0], [2.0]], 0.1)
    np.testing.assert_array_equal(per_run.u[:, :, 0], [[1, 1, 1], [2, 2, 2]])
    assert cldyn.Sequences(np.zeros((2, 3, 2)), None, 0.1).u.shape == (2, 3, 0)
    # integer positions become floating
    assert np.issubdtype(cldyn.Sequences(np.zeros((1, 3, 2), int), dt=0.1).x.dtype, np.floating)


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"x": np.zeros((RUNS, SAMPLES))}, r"x must have shape \(runs, T, k\)"),
        ({"u": np.zeros((RUNS + 1, L))}, "u has 5 runs but x has 4"),
        ({"u": np.zeros((RUNS, SAMPLES - 1, L))}, r"u must have shape \(4, 5, l\)"),
        ({"dt": 0.0}, "dt must be a positive time step"),
        ({"dt": float("nan")}, "dt must be a positive time step"),
        ({"xd": np.zeros((RUNS, SAMPLES, K + 1))}, "xd must have the shape of x"),
        ({"extras": {"qpos": np.zeros((RUNS + 1, SAMPLES))}}, r"extras\['qpos'\] must lead with the run"),
        ({"extras": {"a/b": np.zeros(RUNS)}}, "extras names must be non-empty strings without '/'"),
        ({"info": {"noise": float("nan")}}, "info must hold finite JSON values"),
        ({"info": {"model": object()}}, "info must hold finite JSON values"),
    ],
)
def test_bad_arguments_are_refused_by_name(overrides, message):
    with pytest.raises(ValueError, match=message):
        _data(**overrides)


def test_non_finite_values_are_refused_with_their_index():
    x = np.zeros((RUNS, SAMPLES, K))
    x[2, 3, 1] = np.nan
    with pytest.raises(ValueError, match=r"x contains a NaN or infinite value at .* = \(2, 3, 1\)"):
        cldyn.Sequences(x, dt=DT)
    qpos = np.zeros((RUNS, SAMPLES, 2))
    qpos[1, 0, 0] = np.inf
    with pytest.raises(ValueError, match=r"extras\['qpos'\] contains a NaN or infinite .* = \(1, 0, 0\)"):
        _data(extras={"qpos": qpos})
    with pytest.raises(TypeError, match="Python objects"):
        _data(extras={"names": np.array([object()] * RUNS)})


def test_take_split_and_astype_carry_the_extras():
    data = _data()
    taken = data.take(np.array([2, 0]))
    np.testing.assert_array_equal(taken.x, data.x[[2, 0]])
    np.testing.assert_array_equal(taken.extras["qpos"], data.extras["qpos"][[2, 0]])
    np.testing.assert_array_equal(taken.extras["frames"], data.extras["frames"][[2, 0]])
    np.testing.assert_array_equal(taken.extras["label"], [2, 0])
    assert taken.info == data.info and taken.dt == DT and taken.xdd is None
    first, rest = data.split(3)
    assert first.num_runs == 3 and rest.num_runs == 1
    np.testing.assert_array_equal(rest.extras["label"], [3])
    half, other = data.split(0.5)
    assert half.num_runs == other.num_runs == 2
    with pytest.raises(ValueError, match="need 0 < first < 4"):
        data.split(4)
    single = data.astype(np.float32)
    assert single.x.dtype == single.xd.dtype == single.extras["qpos"].dtype == np.float32
    # integer extras (frames, labels) are not numbers to cast
    assert single.extras["frames"].dtype == np.uint8
    assert single.extras["label"].dtype == data.extras["label"].dtype
    np.testing.assert_array_equal(single.extras["qpos"], data.extras["qpos"].astype(np.float32))


def test_take_under_jit_and_vmap_over_runs():
    data = _data()

    @eqx.filter_jit
    def batch(data, indices):
        return data.take(indices)

    taken = batch(data, jnp.array([3, 1]))
    np.testing.assert_array_equal(taken.extras["qpos"], data.extras["qpos"][[3, 1]])
    sums = jax.vmap(lambda run: jnp.sum(run.x))(data)
    np.testing.assert_allclose(sums, data.x.sum(axis=(1, 2)), rtol=1e-12)


def test_info_is_read_only_json_and_static():
    data = _data()
    assert data.info["joint_names"] == ("a", "b") and data.info["seed"] == 3
    with pytest.raises(TypeError):
        data.info["seed"] = 4  # type: ignore[index]
    with pytest.raises(AttributeError):
        data.info._text = "{}"
    assert np.asarray(data.info["basis"]).shape == (2, 3)
    assert data.info == {"joint_names": ["a", "b"], "seed": 3, "noise": 0.01, "basis": data.info["basis"]}
    assert hash(_data().info) == hash(data.info)
    # numpy values become plain JSON values
    assert cldyn.Sequences(np.zeros((1, 2, 2)), dt=1.0, info={"n": np.int64(3), "v": np.ones(2)}).info == {
        "n": 3, "v": [1.0, 1.0]
    }
    # `info` is static: a jitted function of the data compiles once per distinct metadata
    traces = []

    @eqx.filter_jit
    def total(data):
        traces.append(1)
        return jnp.sum(data.x)

    total(data)
    total(_data(x=np.ones((RUNS, SAMPLES, K))))
    assert len(traces) == 1
    total(_data(info={"seed": 4}))
    assert len(traces) == 2


def test_replace_and_relative_to():
    x_clean = np.arange(RUNS * SAMPLES * K, dtype=float).reshape(RUNS, SAMPLES, K)
    data = _data(x=x_clean + 0.5, extras={"x_clean": x_clean, "qpos": np.zeros((RUNS, SAMPLES, 1))})
    clean = dataclasses.replace(data, x=data.extras["x_clean"], extras={})
    np.testing.assert_array_equal(clean.x, x_clean)
    assert clean.extras == {} and clean.info == data.info
    shifted = data.relative_to([1.0, -2.0])
    # each keypoint [x1, y1, x2, y2] moves by (-1, +2)
    np.testing.assert_array_equal(shifted.x - data.x, np.broadcast_to([-1.0, 2.0, -1.0, 2.0], data.x.shape))
    np.testing.assert_array_equal(shifted.extras["x_clean"], x_clean - [1.0, -2.0, 1.0, -2.0])
    np.testing.assert_array_equal(shifted.xd, data.xd)
    np.testing.assert_array_equal(shifted.extras["qpos"], data.extras["qpos"])
    assert shifted.info["origin"] == (1.0, -2.0)
    assert shifted.relative_to([0.5, 0.5]).info["origin"] == (1.5, -1.5)
    with pytest.raises(ValueError, match="origin has 3 coordinates"):
        data.relative_to([0.0, 0.0, 0.0])


# -- the file ---------------------------------------------------------------------------------------


def test_save_load_round_trip_is_bit_exact(tmp_path):
    data = _data()
    path = data.save(tmp_path / "runs")
    assert path.name == "runs.npz"
    loaded = cldyn.Sequences.load(path)
    _same(data, loaded)
    assert [p.name for p in tmp_path.iterdir()] == ["runs.npz"]  # no temporary file left behind
    # float32 data, JAX arrays, no controls and accelerations: the same
    x = jnp.ones((2, 3, 2), jnp.float32)
    small = cldyn.Sequences(x, None, 0.1, xdd=jnp.zeros_like(x))
    _same(small, cldyn.Sequences.load(small.save(tmp_path / "small.npz")))


def test_save_refuses_to_overwrite(tmp_path):
    data = _data()
    path = data.save(tmp_path / "runs.npz")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="runs.npz: already exists; pass overwrite=True"):
        _data(info={"seed": 9}).save(path)
    assert path.read_bytes() == before
    _data(info={"seed": 9}).save(path, overwrite=True)
    assert cldyn.Sequences.load(path).info["seed"] == 9
    (tmp_path / "folder.npz").mkdir()
    with pytest.raises(IsADirectoryError, match="folder.npz: is a directory"):
        data.save(tmp_path / "folder.npz", overwrite=True)


def _contents(path) -> dict:
    with np.load(path) as npz:
        return dict(npz)


def _rewrite(path, contents: dict, **metadata) -> None:
    meta = json.loads(str(contents["metadata"]))
    meta.update(metadata)
    np.savez(path, **{**contents, "metadata": np.array(json.dumps(meta))})


def test_unreadable_files_are_refused_by_name(tmp_path):
    good = _data().save(tmp_path / "good.npz")
    with pytest.raises(FileNotFoundError, match="nothing.npz: no such file"):
        cldyn.Sequences.load(tmp_path / "nothing.npz")
    (tmp_path / "dir.npz").mkdir()
    with pytest.raises(ValueError, match="dir.npz: not a file"):
        cldyn.Sequences.load(tmp_path / "dir.npz")
    cases = {
        "empty.npz": b"",
        "random.npz": os.urandom(256),
        "truncated.npz": good.read_bytes()[: good.stat().st_size // 2],
        "pickle.npz": pickle.dumps({"x": np.zeros((1, 2, 2))}),
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=f"{name}: ") as error:
            cldyn.Sequences.load(tmp_path / name)
        assert "allow_pickle" not in str(error.value)
    # an archive whose entry is a pickled object array
    np.savez(tmp_path / "objects.npz", metadata=np.array("{}"), x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="objects.npz: entry 'x' holds pickled Python objects") as error:
        cldyn.Sequences.load(tmp_path / "objects.npz")
    assert "allow_pickle" not in str(error.value)
    # a corrupt member inside an intact archive
    raw = bytearray(good.read_bytes())
    middle = len(raw) // 2
    raw[middle : middle + 64] = bytes(64)
    (tmp_path / "damaged.npz").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="damaged.npz: "):
        cldyn.Sequences.load(tmp_path / "damaged.npz")


def test_foreign_and_inconsistent_files_are_refused_by_name(tmp_path):
    path = _data().save(tmp_path / "good.npz")
    contents = _contents(path)
    np.savez(tmp_path / "foreign.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="foreign.npz: not a cldyn data file"):
        cldyn.Sequences.load(tmp_path / "foreign.npz")
    np.savez(tmp_path / "text.npz", **{**contents, "metadata": np.array("{not json")})
    with pytest.raises(ValueError, match="text.npz: corrupt metadata"):
        cldyn.Sequences.load(tmp_path / "text.npz")
    _rewrite(tmp_path / "schema.npz", contents, schema="cldyn.Sequences/99")
    with pytest.raises(ValueError, match="schema.npz: schema 'cldyn.Sequences/99' is not one this version"):
        cldyn.Sequences.load(tmp_path / "schema.npz")
    _rewrite(tmp_path / "dt.npz", contents, dt=-0.02)
    with pytest.raises(ValueError, match="dt.npz: Sequences: dt must be a positive time step"):
        cldyn.Sequences.load(tmp_path / "dt.npz")
    _rewrite(tmp_path / "dtype.npz", contents, dt="0.02")
    with pytest.raises(ValueError, match="dtype.npz: metadata 'dt' is not a number"):
        cldyn.Sequences.load(tmp_path / "dtype.npz")
    _rewrite(tmp_path / "runs.npz", contents, runs=RUNS + 1)
    with pytest.raises(ValueError, match=r"runs.npz: x has shape \(4, 5, 4\), the metadata says 5 runs"):
        cldyn.Sequences.load(tmp_path / "runs.npz")
    missing = {k: v for k, v in contents.items() if k != "extras/qpos"}
    np.savez(tmp_path / "missing.npz", **missing)
    with pytest.raises(ValueError, match=r"missing.npz: missing arrays \['extras/qpos'\]"):
        cldyn.Sequences.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "unlisted.npz", **contents, stray=np.zeros(3))
    with pytest.raises(ValueError, match=r"unlisted.npz: arrays \['stray'\] are not listed"):
        cldyn.Sequences.load(tmp_path / "unlisted.npz")
    np.savez(tmp_path / "shape.npz", **{**contents, "xd": np.zeros((RUNS, SAMPLES, K + 1))})
    with pytest.raises(ValueError, match=r"shape.npz: array 'xd' has shape \(4, 5, 5\) .*, the metadata"):
        cldyn.Sequences.load(tmp_path / "shape.npz")
    # consistent with its metadata, but not with x: the container's own check, with the file's name
    _rewrite(
        tmp_path / "mismatch.npz", {**contents, "xd": np.zeros((RUNS, SAMPLES, K + 1))},
        arrays={**json.loads(str(contents["metadata"]))["arrays"], "xd": [[RUNS, SAMPLES, K + 1], "<f8"]},
    )
    with pytest.raises(ValueError, match="mismatch.npz: Sequences: xd must have the shape of x"):
        cldyn.Sequences.load(tmp_path / "mismatch.npz")


def test_first_version_files_load(tmp_path):
    """`cldyn.Sequences/1`, as `Sequences.save` wrote it before extras and info."""
    x = np.random.default_rng(1).standard_normal((3, 6, 2))
    u = np.ones((3, 6, 1))
    metadata = json.dumps({"schema": "cldyn.Sequences/1", "dt": 0.05})
    np.savez_compressed(tmp_path / "old.npz", metadata=np.array(metadata), x=x, u=u, xd=2 * x)
    loaded = cldyn.Sequences.load(tmp_path / "old.npz")
    np.testing.assert_array_equal(loaded.x, x)
    np.testing.assert_array_equal(loaded.xd, 2 * x)
    assert loaded.dt == 0.05 and loaded.xdd is None and loaded.extras == {} and loaded.info == {}
