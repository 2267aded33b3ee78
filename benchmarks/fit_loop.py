"""Which step loop trains faster here: `cldyn.CompiledLoop` (the chunk as one `lax.while_loop`) or
`cldyn.HostLoop` (one compiled step at a time, dispatched asynchronously)?

Three jobs, each timed with both loops through `cldyn.fit` in the same run (the loops interleaved):
keyvision's autoencoder of appendix A.4 on 64x64 frames (U-Net estimator and renderer, the
reconstruction loss; images per second), its joint stage (windows of frames, the reconstruction plus
the dynamics loss on their keypoints; images per second), and KeyCLD's pendulum dynamics on keypoint
states (the collocation loss; steps per second). `keyvision train --loop` chooses the loop of the
stages of images; run this on a machine to choose it there. Each fit is timed after a first one
that compiles it. Prints one JSON object and writes `benchmarks/results/fit_loop.json`.

    python benchmarks/fit_loop.py [--quick]
"""

import argparse
import sys
import time

import equinox as eqx
import jax
import numpy as np
import optax

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import machine, write

import cldyn
import keyvision

LOOPS = {"compiled": cldyn.CompiledLoop(), "host": cldyn.HostLoop()}


def _images_job(width: int, batch: int):
    keys = jax.random.split(jax.random.key(0), 3)
    model = keyvision.KeyCLD(
        keyvision.KeypointEstimator(1, width=width, key=keys[0]),
        cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=keys[1]),
        keyvision.Renderer(1, width=width, key=keys[2]),
    )
    frames = np.random.default_rng(0).integers(0, 256, (64, 8, 64, 64, 3), dtype=np.uint8)
    data = keyvision.ImageSequences(frames, np.zeros((64, 1), np.float32), 0.02)

    def networks(model):
        spec = jax.tree.map(eqx.is_inexact_array, model)
        return eqx.tree_at(lambda m: m.dynamics, spec, replace=False)

    options = {"loss": keyvision.Reconstruction(), "batching": cldyn.Windows(batch, 1), "trainable": networks}
    return model, data, options, batch


def _joint_job(width: int, batch: int, window: int):
    # the joint stage (c) of `keyvision.train` with the table's recipe: windows of frames, the
    # reconstruction plus the collocation loss on their keypoints (weight 60 dt^4), everything trained
    model, data, _, _ = _images_job(width, batch)
    windows = np.random.default_rng(1).integers(0, 256, (64, window, 64, 64, 3), dtype=np.uint8)
    data = keyvision.ImageSequences(windows, np.zeros((64, window, 1), np.float32), 0.02)
    loss = keyvision.Reconstruction() + 60 * 0.02**4 * keyvision.KeypointDynamics(cldyn.Collocation())
    return model, data, {"loss": loss, "batching": cldyn.Windows(batch, window)}, batch * window


def _states_job():
    rng = np.random.default_rng(0)
    angles = rng.uniform(-np.pi, np.pi, (64, 1)) + 0.05 * np.arange(50)[None, :]
    x = np.stack([np.sin(angles), -np.cos(angles)], axis=-1).astype(np.float32)
    data = cldyn.Sequences(x, np.zeros((64, 50, 1), np.float32), 0.02)
    model = cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=jax.random.key(0))
    return model, data, {"loss": cldyn.Collocation(), "batching": cldyn.Runs(32)}, 1


def _time(job, steps: int, repeats: int) -> dict:
    model, data, options, per_step = job
    seconds = {name: [] for name in LOOPS}
    for name, loop in LOOPS.items():  # compile
        cldyn.fit(model, data, steps=steps, key=jax.random.key(1), optimizer=optax.adam(1e-3),
                  log_every=steps, validate_every=steps, loop=loop, **options)
    for _ in range(repeats):
        for name, loop in LOOPS.items():
            start = time.perf_counter()
            cldyn.fit(model, data, steps=steps, key=jax.random.key(1), optimizer=optax.adam(1e-3),
                      log_every=steps, validate_every=steps, loop=loop, **options)
            seconds[name].append(time.perf_counter() - start)
    rates = {name: per_step * steps / min(values) for name, values in seconds.items()}
    return {**{f"{name}_per_s": round(rate, 2) for name, rate in rates.items()},
            "host_over_compiled": round(rates["host"] / rates["compiled"], 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps and repeats (a smoke test)")
    args = parser.parse_args()
    repeats = 1 if args.quick else 3
    rows = []
    for width in (8,) if args.quick else (8, 16):
        row = _time(_images_job(width, 16), steps=4 if args.quick else 20, repeats=repeats)
        rows.append({"job": f"autoencoder 64x64, width {width}, batch 16", "unit": "images", **row})
        print(rows[-1], file=sys.stderr, flush=True)
    width = 8 if args.quick else 16
    row = _time(_joint_job(width, 4, 10), steps=4, repeats=repeats)
    rows.append({"job": f"joint stage 64x64, width {width}, 4 windows of 10", "unit": "images", **row})
    print(rows[-1], file=sys.stderr, flush=True)
    row = _time(_states_job(), steps=50 if args.quick else 500, repeats=repeats)
    rows.append({"job": "KeyCLD pendulum on states, collocation, batch 32", "unit": "steps", **row})
    print(rows[-1], file=sys.stderr, flush=True)
    result = {
        "benchmark": "fit_loop",
        "what": "cldyn.fit throughput with CompiledLoop and HostLoop, the fastest of the repeats, "
        "float32, after a first fit that compiles",
        "machine": machine(),
        "rows": rows,
    }
    if args.quick:
        print(result)
    else:
        write("fit_loop", result)


if __name__ == "__main__":
    main()
