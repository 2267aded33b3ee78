"""What identify's held-out rollouts cost to compile and to run: its own rollout loop against
`cldyn.rollout` in the same Gauss-Newton fit of the initial states.

identify rolls out every trial model it builds (the nominal model, each augmented and refitted one)
from the first states of the held-out runs, fitting each initial state to the first 0.2 s
(`cldyn._identify.errors._rollout_batch`). Every trial model has a new structure, so each compiles
anew, and on a CPU the compilation is most of the cost of a rollout. identify integrates
`cldyn.rollout`'s scheme (RK4 at the sampling interval, `Projection` after every step, controls held)
in a scan of its own with RK4's four stages looped, the runs batched by `vmap`; the reference
here is the same fit with identify's rollouts as they were before (2026-11-28): `cldyn.rollout`
(diffrax), one run after another (`lax.map`). Both give the same positions to rounding
(`tests/test_identify.py::test_identifys_rollouts_are_cldyns_rollouts`).

The runs (12 of 1 s at 100 Hz from random states, by `cldyn.rollout`, with 1 mm noise on the
measurement) are made in this process; each scene and implementation is timed in a fresh one, which
has not rolled the model out before: the first call, with a model that has keypoint drag
(zero) added (the process's first rollout: tracing, compiling, one fit); then the call with the
scene's model, a new structure in a process that has rolled out before, as each trial model of
identify is (the headline figure); then the median of three more calls with it (the fit alone).
The ratio to the reference in the same run is the result.

Writes benchmarks/results/identify_compile.json and identify_compile.md; prints the JSON.

    python benchmarks/identify_compile.py
"""

import json
import os
import pathlib
import subprocess
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

import cldyn

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import machine, write  # noqa: E402

SCENES = ("pendulum", "cartpole", "acrobot")
RUNS, SAMPLES, DT, WINDOW = 12, 101, 0.01, 20

_ONE = """
import json, statistics, sys, time
import equinox as eqx, jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import cldyn
from cldyn._identify import errors
scene, which, path = sys.argv[1], sys.argv[2], sys.argv[3]
system, _ = getattr(cldyn.systems, scene)()
# the runs come from the parent process: no rollout of this model here before the timed calls
saved = np.load(path)
x0, xd0, us, truth, measured = (jnp.asarray(saved[k]) for k in ("x0", "xd0", "us", "truth", "measured"))
def previous(model, states, controls, dt):  # identify's rollouts before 2026-11-28
    k = states.shape[1] // 2
    return jax.lax.map(
        lambda a: cldyn.rollout(model, a[0][:k], a[0][k:], a[1], dt, throw=False).x, (states, controls)
    )
options = {{}} if which == "identify" else {{"roll": previous}}
valid = jnp.ones(({runs}, {window} + 1), bool)
def call(model):
    start = time.perf_counter()
    xs, converged = errors._rollout_batch(model, x0, xd0, us, {dt}, measured, {window}, valid, **options)
    xs.block_until_ready()
    return time.perf_counter() - start, xs, converged
# identify's situation: a model of a new structure in a process that has rolled out others before
size = system.size // 2
dragged = eqx.tree_at(lambda s: s.dissipation, system, cldyn.KeypointDrag(jnp.zeros(size), jnp.zeros(size)),
                      is_leaf=lambda v: v is None)
first = call(dragged)[0]
new, xs, converged = call(system)
again = statistics.median(call(system)[0] for _ in range(3))
print(json.dumps({{"first_call_s": first, "new_model_s": new, "call_s": again,
                  "converged": int(converged.sum()), "error_m": float(jnp.max(jnp.abs(xs - truth)))}}))
"""


def runs(scene: str, path: pathlib.Path) -> None:
    """The scene's runs from random states (`cldyn.rollout`), with 1 mm noise, saved to `path`."""
    system, joints = getattr(cldyn.systems, scene)()
    rng = np.random.default_rng(0)
    m = joints.num_joints
    x0, xd0 = jax.vmap(joints.to_keypoints)(
        jnp.asarray(rng.uniform(-1, 1, (RUNS, m))), jnp.asarray(rng.uniform(-1, 1, (RUNS, m)))
    )
    us = rng.uniform(-1, 1, (RUNS, SAMPLES, system.num_inputs))
    roll = jax.vmap(lambda a, b, c: cldyn.rollout(system, a, b, c, DT).x)
    truth = np.asarray(roll(x0, xd0, jnp.asarray(us)))
    measured = truth + 1e-3 * rng.standard_normal(truth.shape)
    np.savez(path, x0=np.asarray(x0), xd0=np.asarray(xd0), us=us, truth=truth, measured=measured)


def measure(scene: str, which: str, path: pathlib.Path) -> dict:
    script = _ONE.format(runs=RUNS, dt=DT, window=WINDOW)
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    done = subprocess.run(
        [sys.executable, "-c", script, scene, which, str(path)], capture_output=True, text=True, env=env,
        check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    rows = []
    for scene in SCENES:
        with tempfile.TemporaryDirectory() as folder:
            path = pathlib.Path(folder) / "runs.npz"
            runs(scene, path)
            own, reference = measure(scene, "identify", path), measure(scene, "reference", path)
        rows.append(
            {
                "scene": scene,
                "identify": own,
                "previous": reference,
                "first_call_ratio": own["first_call_s"] / reference["first_call_s"],
                "new_model_ratio": own["new_model_s"] / reference["new_model_s"],
                "call_ratio": own["call_s"] / reference["call_s"],
            }
        )
        print(scene, json.dumps(rows[-1]), file=sys.stderr, flush=True)
    lines = [
        "# identify's held-out rollouts: compile and run time",
        "",
        f"`_rollout_batch` on {RUNS} runs of {SAMPLES} samples at {DT} s (initial states fitted to the first "
        f"{WINDOW} samples), each implementation in a fresh process: identify's rollout loop, and identify's "
        "rollouts before 2026-11-28 (`cldyn.rollout`, one run after another); ratio identify / previous. "
        "A new model: the call with the scene's model after one with another structure, as identify meets "
        "each trial model. The process's first: that first call. The fit alone: the median of three more "
        "calls. Written by `benchmarks/identify_compile.py`.",
        "",
        "| scene | a new model (trace + compile + fit): identify | previous | ratio | "
        "the process's first: identify | previous | ratio | "
        "the fit alone: identify | previous | ratio | runs converged |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        a, b = r["identify"], r["previous"]
        lines.append(
            f"| {r['scene']} | {a['new_model_s']:.2f} s | {b['new_model_s']:.2f} s | "
            f"{r['new_model_ratio']:.2f} | {a['first_call_s']:.2f} s | {b['first_call_s']:.2f} s | "
            f"{r['first_call_ratio']:.2f} "
            f"| {1e3 * a['call_s']:.0f} ms | {1e3 * b['call_s']:.0f} ms | {r['call_ratio']:.2f} | "
            f"{a['converged']} / {b['converged']} of {RUNS} |"
        )
    result = {"benchmark": "identify_compile", "machine": machine(), "rows": rows}
    write("identify_compile", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
