"""Acceleration evaluations per second for the acrobot: eq. 6 in keypoint coordinates.

Reference, timed in the same run: the same acrobot in generalised coordinates, with the accelerations
of the Euler-Lagrange equations by automatic differentiation of L(q, qd) (the approach of Deep
Lagrangian Networks; DeLaN's README reports 1517 Hz for a one-step prediction of one sample). Both
single-sample (jit, one call per sample, dispatch included) and batched (vmap over 4096 states).

    python benchmarks/acceleration.py
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import machine, write  # noqa: E402

jax.config.update("jax_enable_x64", True)

import cldyn  # noqa: E402

BATCH = 4096
SINGLE_CALLS = 20_000


def generalised_acrobot(masses=(1.0, 1.0), lengths=(1.0, 1.0)):
    """`qdd(q, qd, u)` of the point-mass acrobot from L(q, qd) by autodiff (DeLaN-style)."""
    m, length = jnp.asarray(masses), jnp.asarray(lengths)

    def lagrangian(q, qd):
        def points(q):
            theta = jnp.cumsum(q)
            d = jnp.stack([jnp.sin(theta), -jnp.cos(theta)], axis=1) * length[:, None]
            return jnp.cumsum(d, axis=0)

        p, v = jax.jvp(points, (q,), (qd,))
        return 0.5 * jnp.sum(m * jnp.sum(v**2, axis=1)) - 9.81 * jnp.sum(m * p[:, 1])

    def qdd(q, qd, u):
        mass = jax.hessian(lagrangian, argnums=1)(q, qd)
        mixed = jax.jacfwd(jax.grad(lagrangian, argnums=1), argnums=0)(q, qd)
        rhs = jax.grad(lagrangian, argnums=0)(q, qd) - mixed @ qd + jnp.array([0.0, u[0]])
        return jnp.linalg.solve(mass, rhs)

    return qdd


def rate_single(fn, args, calls=SINGLE_CALLS):
    jax.block_until_ready(fn(*args))
    start = time.perf_counter()
    for _ in range(calls):
        out = fn(*args)
    jax.block_until_ready(out)
    return calls / (time.perf_counter() - start)


def rate_batched(fn, args, repeats=50):
    jax.block_until_ready(fn(*args))
    best = np.inf
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeats):
            out = fn(*args)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - start) / repeats)
    return BATCH / best


def main():
    system, joints = cldyn.systems.acrobot()
    key = jax.random.key(0)
    q = jax.random.uniform(key, (BATCH, 2), minval=-np.pi, maxval=np.pi)
    qd = jax.random.normal(jax.random.key(1), (BATCH, 2))
    u = jax.random.normal(jax.random.key(2), (BATCH, 1))
    x, xd = jax.vmap(joints.to_keypoints)(q, qd)
    reference = generalised_acrobot()

    keypoint_single = jax.jit(lambda x, xd, u: system.acceleration(x, xd, u))
    general_single = jax.jit(reference)
    keypoint_batched = jax.jit(jax.vmap(lambda x, xd, u: system.acceleration(x, xd, u)))
    general_batched = jax.jit(jax.vmap(reference))

    result = {
        "benchmark": "acceleration",
        "system": "acrobot (cldyn.systems.acrobot, 2 links, 4 keypoint coordinates, 2 constraints)",
        "dtype": "float64",
        "single_per_second": {
            "cldyn_eq6": rate_single(keypoint_single, (x[0], xd[0], u[0])),
            "generalised_autodiff_reference": rate_single(general_single, (q[0], qd[0], u[0])),
        },
        "batched_per_second": {
            "cldyn_eq6": rate_batched(keypoint_batched, (x, xd, u)),
            "generalised_autodiff_reference": rate_batched(general_batched, (q, qd, u)),
        },
        "batch": BATCH,
        "delan_readme_single_hz": 1517.4,
        "machine": machine(),
    }
    for kind in ("single_per_second", "batched_per_second"):
        r = result[kind]
        r["ratio"] = r["cldyn_eq6"] / r["generalised_autodiff_reference"]
    write("acceleration", result)


if __name__ == "__main__":
    main()
