"""Rollout throughput: cldyn vs MuJoCo on dm_control's acrobot.

1024 rollouts of 1000 steps of dt = 0.01 s, RK4, from random initial states, every state saved: cldyn
(`simulate` with `Projection` stabilisation, vmapped, float64) on `from_mjcf("acrobot")`, and MuJoCo's
`mujoco.rollout` on the same model with its joint damping set to 0 (so that both integrate the same
dynamics), RK4 at the same dt, one thread per core. Both timed in the same run, best of 3; also single
trajectories (one rollout of 1000 steps). Prints steps per second and the ratio.

    python benchmarks/throughput.py
"""

import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import machine, write  # noqa: E402

jax.config.update("jax_enable_x64", True)

import mujoco  # noqa: E402
from mujoco import rollout  # noqa: E402

import cldyn  # noqa: E402
from cldyn.mujoco import from_mjcf, scene_xml  # noqa: E402

BATCH, STEPS, DT = 1024, 1000, 0.01


def best_of(fn, repeats=3):
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main():
    rng = np.random.default_rng(0)
    qpos = rng.uniform(-np.pi, np.pi, size=(BATCH, 2))
    qvel = rng.uniform(-0.1, 0.1, size=(BATCH, 2))

    # MuJoCo
    model = mujoco.MjModel.from_xml_string(scene_xml("acrobot"))
    model.dof_damping[:] = 0.0
    model.opt.timestep = DT
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    threads = os.cpu_count() or 1
    datas = [mujoco.MjData(model) for _ in range(threads)]
    size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    state = np.zeros((BATCH, size))
    data = mujoco.MjData(model)
    for i in range(BATCH):
        data.qpos[:], data.qvel[:] = qpos[i], qvel[i]
        mujoco.mj_getState(model, data, state[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    control = np.zeros((BATCH, STEPS, model.nu))
    with rollout.Rollout(nthread=threads) as runner:
        mj_batch = best_of(lambda: runner.rollout(model, datas, state, control))
    with rollout.Rollout(nthread=1) as runner:
        mj_single = best_of(lambda: runner.rollout(model, datas[:1], state[:1], control[:1]))

    # cldyn
    bridge = from_mjcf("acrobot")
    x0, xd0 = jax.vmap(bridge.joints.to_keypoints)(jnp.asarray(qpos), jnp.asarray(qvel))
    ts = jnp.arange(STEPS + 1) * DT

    def one(x0, xd0):
        return cldyn.simulate(bridge.system, x0, xd0, ts, solver=cldyn.RK4(), dt0=DT, max_steps=STEPS + 2).x

    batched = eqx.filter_jit(jax.vmap(one))
    single = eqx.filter_jit(one)
    cl_batch = best_of(lambda: jax.block_until_ready(batched(x0, xd0)))
    cl_single = best_of(lambda: jax.block_until_ready(single(x0[0], xd0[0])))

    # the two agree: same dynamics, same integrator (on a non-chaotic start, over the first second)
    check = np.asarray(single(x0[0], xd0[0]))[:101]
    with rollout.Rollout(nthread=1) as runner:
        states, _ = runner.rollout(model, datas[:1], state[:1], control[:1, :100])
    mj_qpos = states[0, :, 1:3]
    mj_x = np.asarray(jax.vmap(bridge.joints.keypoints)(jnp.asarray(mj_qpos)))
    agreement = float(np.max(np.abs(mj_x - check[1:101])))

    steps = BATCH * STEPS
    result = {
        "benchmark": "throughput",
        "system": "dm_control acrobot, damping 0, RK4, dt 0.01",
        "rollouts": BATCH,
        "steps_per_rollout": STEPS,
        "batched_steps_per_second": {
            "cldyn_projection": steps / cl_batch,
            "mujoco_rollout": steps / mj_batch,
        },
        "single_steps_per_second": {
            "cldyn_projection": STEPS / cl_single,
            "mujoco_rollout": STEPS / mj_single,
        },
        "mujoco_threads": threads,
        "max_keypoint_difference_first_second_m": agreement,
        "machine": machine(),
    }
    for kind in ("batched_steps_per_second", "single_steps_per_second"):
        r = result[kind]
        r["ratio"] = r["cldyn_projection"] / r["mujoco_rollout"]
    write("throughput", result)


if __name__ == "__main__":
    main()
