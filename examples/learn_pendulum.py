"""Learn KeyCLD's pendulum from keypoint states recorded with MuJoCo, then roll it out on held-out runs.

The paper's protocol (appendix A.6, 500 runs x 50 frames of the fully actuated KeyCLD pendulum; the
first 450 train), the paper's model (a point mass, an MLP potential, an MLP input matrix and an
`Anchor` constraint) and its collocation loss (eq. 11-13, with fourth-order stencils, which suit
noise-free states). About a minute on 2 CPU cores.

    python examples/learn_pendulum.py [--out runs/pendulum]
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import cldyn
import cldyn.mujoco


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="runs/learn_pendulum", help="output directory")
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args()

    data = cldyn.mujoco.keycld_dataset("pendulum", seed=0)  # keypoints about the pivot, dt = 0.02 s
    train, validation = data.split(450)
    model = cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=jax.random.key(0))
    result = cldyn.fit(
        model, train, loss=cldyn.Collocation(order=4), steps=args.steps, batching=cldyn.Runs(32),
        key=jax.random.key(1), validation=validation, validate_every=500, out=args.out,
        progress_meter=cldyn.TextProgressMeter(),
    )
    print(f"trained in {result.seconds:.1f} s; last record {result.history[-1]}")

    jax.config.update("jax_enable_x64", True)  # evaluate in float64
    model = jax.tree.map(lambda a: a.astype(jnp.float64) if isinstance(a, jax.Array) else a, result.model)
    test = cldyn.mujoco.keycld_dataset("pendulum", runs=50, frames=53, seed=1)  # 50 runs of 1 s
    scale = cldyn.range_of_motion(test.x)
    evaluation = cldyn.evaluate(model, test, threshold=0.1 * scale)
    print(f"learned keypoint mass: {float(model.mass.masses[0]):.3f} kg")
    horizon = float(evaluation.ts[-1])  # the rollouts start at the second frame of each run
    print(f"valid prediction time: {np.mean(evaluation.vpt_seconds):.2f} s of {horizon:.2f} s")
    error = 100 * np.mean(evaluation.error_over(1.0)) / scale
    print(f"RMS keypoint error over 1 s: {error:.2f}% of the range of motion")


if __name__ == "__main__":
    main()
