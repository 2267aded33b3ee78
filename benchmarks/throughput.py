"""Rollout throughput: cldyn against `mujoco.rollout` and MJX on dm_control's acrobot.

Rollouts of dt = 0.01 s, RK4, from random initial states, every state saved, at several batch sizes:

- cldyn: `simulate` with `Projection` stabilisation on `from_mjcf("acrobot")`, vmapped over the
  batch, in float64 and float32 (system and states cast), on JAX's default backend;
- MuJoCo: `mujoco.rollout` on the same model with its joint damping set to 0 (so that all engines
  integrate the same dynamics), RK4 at the same dt, one thread per core (one thread for batch 1);
- MJX (`mujoco-mjx`, the `bench` extra): `mjx.step` of the same model in a `lax.scan`, vmapped over
  the batch, jitted, on the same backend as cldyn, in float32 and float64.

Batch 1 is one trajectory: a plain call for every engine, not a vmapped batch of one.

A batch of `B` rollouts runs `min(steps, budget // B)` steps (at least 20), the same for every engine,
so that the large batches finish on a small machine; throughput is steps per second over all
rollouts. Every engine is compiled and run once first, then the engines are timed in turn, `repeats`
rounds, and the median is reported with its ratio to `mujoco.rollout` in the same run (absolute times
drift on shared machines; the ratios are the result). The agreement between engines is the largest
keypoint difference from MuJoCo over the first second of one non-chaotic rollout.

Writes benchmarks/results/throughput.json and throughput.md and prints the JSON.

    python benchmarks/throughput.py [--batches 1 1024 8192 65536] [--budget 1024000] [--note TEXT]
"""

import argparse
import json
import os
import subprocess
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
import mujoco  # noqa: E402
from _common import machine, write  # noqa: E402
from mujoco import mjx, rollout  # noqa: E402

import cldyn  # noqa: E402
from cldyn.mujoco import from_mjcf, scene_xml  # noqa: E402

DT = 0.01
MIN_STEPS = 20
AGREEMENT_START = (0.6, -0.3)  # joint angles (rad), released from rest: not chaotic over 1 s


def mujoco_model():
    model = mujoco.MjModel.from_xml_string(scene_xml("acrobot"))
    model.dof_damping[:] = 0.0
    model.opt.timestep = DT
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    # dm_control's acrobot asks for energies, which MJX does not compute; they do not enter the dynamics
    model.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    return model


def cast(tree, dtype):
    """Every floating array in `tree` (JAX or NumPy: an MJX model holds both) as `dtype`."""
    floating = lambda v: isinstance(v, jax.Array | np.ndarray) and jnp.issubdtype(v.dtype, jnp.floating)
    return jax.tree.map(lambda v: v.astype(dtype) if floating(v) else v, tree)


def mujoco_engine(model, qpos, qvel, steps):
    """`mujoco.rollout` of the batch: a function of no arguments that runs it, and the `Rollout`
    (a context manager that holds its threads)."""
    batch = qpos.shape[0]
    threads = 1 if batch == 1 else (os.cpu_count() or 1)
    datas = [mujoco.MjData(model) for _ in range(threads)]
    size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    state = np.zeros((batch, size))
    data = mujoco.MjData(model)
    for i in range(batch):
        data.qpos[:], data.qvel[:] = qpos[i], qvel[i]
        mujoco.mj_getState(model, data, state[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    control = np.zeros((batch, steps, model.nu))
    runner = rollout.Rollout(nthread=threads)

    def run():
        return runner.rollout(model, datas, state, control)

    return run, runner


def mjx_rollout(model, qpos, qvel, steps, dtype):
    """MJX: `mjx.step` in a scan, vmapped over the batch and jitted; returns a function of no
    arguments that gives the joint positions of every rollout after every step."""
    mx = cast(mjx.put_model(model), dtype)
    template = cast(mjx.make_data(mx), dtype)

    def one(q, v):
        def step(data, _):
            data = mjx.step(mx, data)
            return data, data.qpos

        return jax.lax.scan(step, template.replace(qpos=q, qvel=v), None, length=steps)[1]

    q, v = jnp.asarray(qpos, dtype), jnp.asarray(qvel, dtype)
    if q.shape[0] == 1:  # one trajectory: not a vmapped batch of one
        fn = jax.jit(one)
        return lambda: jax.block_until_ready(fn(q[0], v[0]))[None]
    fn = jax.jit(jax.vmap(one))
    return lambda: jax.block_until_ready(fn(q, v))


def cldyn_rollout(bridge, qpos, qvel, steps, dtype):
    """cldyn: `simulate` vmapped over the batch and jitted; returns a function of no arguments that
    gives the keypoints of every rollout at every step (the start included)."""
    system = cast(bridge.system, dtype)
    x0, xd0 = jax.vmap(bridge.joints.to_keypoints)(jnp.asarray(qpos), jnp.asarray(qvel))
    x0, xd0 = x0.astype(dtype), xd0.astype(dtype)
    ts = jnp.arange(steps + 1, dtype=dtype) * jnp.asarray(DT, dtype)

    def one(x, xd):
        return cldyn.simulate(system, x, xd, ts, solver=cldyn.RK4(), dt0=DT).x

    if x0.shape[0] == 1:  # one trajectory: not a vmapped batch of one
        fn = eqx.filter_jit(one)
        return lambda: jax.block_until_ready(fn(x0[0], xd0[0]))[None]
    fn = eqx.filter_jit(jax.vmap(one))
    return lambda: jax.block_until_ready(fn(x0, xd0))


def measure(engines: dict, repeats: int) -> dict:
    """Median seconds of each engine, timed in turn (interleaved) over `repeats` rounds."""
    for run in engines.values():
        run()  # compile, warm up
    times = {name: [] for name in engines}
    for _ in range(repeats):
        for name, run in engines.items():
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    return {name: float(np.median(t)) for name, t in times.items()}


def agreement(model, bridge, q0, dtype) -> dict:
    """Largest keypoint difference (m) from MuJoCo over the first second of one rollout from rest at
    the joint angles `q0`."""
    steps = int(round(1.0 / DT))
    qpos, qvel = np.asarray(q0, dtype=float)[None], np.zeros((1, 2))
    run, runner = mujoco_engine(model, qpos, qvel, steps)
    with runner:
        states, _ = run()
    keypoints = lambda q: np.asarray(jax.vmap(bridge.joints.keypoints)(jnp.asarray(q, dtype)), np.float64)
    reference = keypoints(states[0, :, 1:3])
    xs = np.asarray(cldyn_rollout(bridge, qpos, qvel, steps, dtype)()[0, 1:], np.float64)
    mjx_x = keypoints(mjx_rollout(model, qpos, qvel, steps, dtype)()[0])
    name = np.dtype(dtype).name
    return {
        f"cldyn_{name}": float(np.max(np.abs(xs - reference))),
        f"mjx_{name}": float(np.max(np.abs(mjx_x - reference))),
    }


def run_pass(args, dtype) -> dict:
    """cldyn and MJX in `dtype`, and `mujoco.rollout` beside them, at every batch size."""
    model, bridge = mujoco_model(), from_mjcf("acrobot")
    name = np.dtype(dtype).name
    rng = np.random.default_rng(0)
    rows = []
    for batch in args.batches:
        steps = max(MIN_STEPS, min(args.steps, args.budget // batch))
        qpos = rng.uniform(-np.pi, np.pi, size=(batch, 2))
        qvel = rng.uniform(-0.1, 0.1, size=(batch, 2))
        mj_run, runner = mujoco_engine(model, qpos, qvel, steps)
        engines = {
            "mujoco_rollout": mj_run,
            f"cldyn_{name}": cldyn_rollout(bridge, qpos, qvel, steps, dtype),
            f"mjx_{name}": mjx_rollout(model, qpos, qvel, steps, dtype),
        }
        with runner:
            seconds = measure(engines, args.repeats)
        sps = {engine: batch * steps / s for engine, s in seconds.items()}
        rows.append({"batch": batch, "steps": steps, "steps_per_second": sps})
        figures = ", ".join(f"{engine} {value:,.0f}" for engine, value in sps.items())
        print(f"{name}, batch {batch}: {figures}", file=sys.stderr)
    return {"rows": rows, "agreement": agreement(model, bridge, AGREEMENT_START, dtype)}


def markdown(result: dict) -> str:
    lines = [
        "# Rollout throughput: cldyn, `mujoco.rollout`, MJX",
        "",
        f"{result['system']}; backend `{result['machine']['backend']}`, {result['machine']['cpus']} CPUs "
        f"({result['note']}). Steps per second over all rollouts, median of {result['repeats']} interleaved "
        "rounds; in brackets the ratio to `mujoco.rollout` in the same process, timed in turn with it (the "
        "float64 and float32 columns come from two processes, each with its own `mujoco.rollout` timing; the "
        "last column is the float64 one). Large batches run fewer steps per rollout (the same for every "
        "engine) to fit the time of a run.",
        "",
        "| batch | steps | cldyn float64 | cldyn float32 | MJX float64 | MJX float32 | `mujoco.rollout` |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in result["rows"]:
        sps = row["steps_per_second"]
        cell = lambda name: f"{sps[name]:,.0f} ({row['ratio_to_mujoco_rollout'][name]:.2f}x)"
        lines.append(
            f"| {row['batch']:,} | {row['steps']} | {cell('cldyn_float64')} | {cell('cldyn_float32')} | "
            f"{cell('mjx_float64')} | {cell('mjx_float32')} | {sps['mujoco_rollout']:,.0f} "
            f"({row['mujoco_threads']} thread{'s' if row['mujoco_threads'] > 1 else ''}) |"
        )
    differences = result["max_keypoint_difference_from_mujoco_first_second_m"]
    agree = ", ".join(f"{name} {value:.2g}" for name, value in differences.items())
    lines += ["", f"Largest keypoint difference from MuJoCo over the first second (m): {agree}.", ""]
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 1024, 8192, 65536])
    parser.add_argument("--steps", type=int, default=1000, help="steps per rollout, at most")
    parser.add_argument("--budget", type=int, default=1_024_000, help="steps per batch, at most")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--note", default="", help="how the machine was shared, for the results")
    parser.add_argument("--only", choices=["float32", "float64"], help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.only is not None:  # one pass, in a process of its own, printed for the parent
        jax.config.update("jax_enable_x64", args.only == "float64")
        print(json.dumps(run_pass(args, jnp.dtype(args.only))))
        return
    # Each precision runs in a process with JAX's x64 mode set as its users would set it (MJX's
    # float32 step does not trace with x64 on), with `mujoco.rollout` timed beside it.
    passes = {}
    for dtype in ("float64", "float32"):
        command = [sys.executable, __file__, "--only", dtype, "--repeats", str(args.repeats)]
        command += ["--steps", str(args.steps), "--budget", str(args.budget), "--batches"]
        command += [str(b) for b in args.batches]
        out = subprocess.run(command, check=True, stdout=subprocess.PIPE, text=True).stdout
        passes[dtype] = json.loads(out.strip().splitlines()[-1])

    rows = []
    for row64, row32 in zip(passes["float64"]["rows"], passes["float32"]["rows"]):
        sps64, sps32 = row64["steps_per_second"], row32["steps_per_second"]
        rows.append(
            {
                "batch": row64["batch"],
                "steps": row64["steps"],
                "mujoco_threads": 1 if row64["batch"] == 1 else (os.cpu_count() or 1),
                "steps_per_second": {
                    "cldyn_float64": sps64["cldyn_float64"],
                    "cldyn_float32": sps32["cldyn_float32"],
                    "mjx_float64": sps64["mjx_float64"],
                    "mjx_float32": sps32["mjx_float32"],
                    "mujoco_rollout": sps64["mujoco_rollout"],
                    "mujoco_rollout_beside_float32": sps32["mujoco_rollout"],
                },
                # each against mujoco.rollout timed in the same process, interleaved with it
                "ratio_to_mujoco_rollout": {
                    "cldyn_float64": sps64["cldyn_float64"] / sps64["mujoco_rollout"],
                    "cldyn_float32": sps32["cldyn_float32"] / sps32["mujoco_rollout"],
                    "mjx_float64": sps64["mjx_float64"] / sps64["mujoco_rollout"],
                    "mjx_float32": sps32["mjx_float32"] / sps32["mujoco_rollout"],
                },
            }
        )
    result = {
        "benchmark": "throughput",
        "system": "dm_control acrobot, damping 0, RK4, dt 0.01 s; cldyn with Projection",
        "repeats": args.repeats,
        "note": args.note or "machine not marked as shared",
        "rows": rows,
        "max_keypoint_difference_from_mujoco_first_second_m": {
            **passes["float64"]["agreement"],
            **passes["float32"]["agreement"],
        },
        "mujoco": mujoco.__version__,
        "machine": machine(),
    }
    write("throughput", result, markdown(result))


if __name__ == "__main__":
    main()
