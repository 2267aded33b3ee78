"""Constraint drift and energy error over long simulations: none / Baumgarte / Projection / RATTLE.

The acrobot (cldyn.systems.acrobot: point masses at the link ends) from chaotic starts (both links
released from rest at large angles), 1e5 steps of dt = 0.01 s (1000 s), no input. Reported per method:
the largest constraint error max |Phi(x) - Phi(x0)| and the largest relative energy error
|E - E0| / (E0 - E_rest), where E_rest is the energy hanging at rest (so the ratio is relative to the
energy the motion actually has), plus the same over the first and the last tenth of the run, which
shows secular growth or its absence.

Writes benchmarks/results/drift.json and drift.md and prints the JSON.

    python benchmarks/drift.py [--steps 100000]
"""

import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import RESULTS, machine, write  # noqa: E402

jax.config.update("jax_enable_x64", True)

import cldyn  # noqa: E402

STARTS = ((1.0, 0.5), (2.0, -1.0), (-2.5, 2.0), (3.0, 0.3))
DT = 0.01


def methods():
    return {
        "none (RK4)": dict(solver=cldyn.RK4(), stabilisation=None),
        "Baumgarte (RK4, alpha=beta=10)": dict(solver=cldyn.RK4(), stabilisation=cldyn.Baumgarte(10.0, 10.0)),
        "Projection (RK4)": dict(solver=cldyn.RK4(), stabilisation=cldyn.Projection()),
        "RATTLE": dict(solver=cldyn.RATTLE(), stabilisation=None),
        "RATTLE, order 4 (Suzuki composition)": dict(solver=cldyn.RATTLE4(), stabilisation=None),
    }


def run(system, joints, steps, kwargs):
    ts = jnp.arange(steps + 1) * DT
    rest = system.energy(*joints.to_keypoints(jnp.zeros(2), jnp.zeros(2)))
    rows = []
    for q0 in STARTS:
        x0, xd0 = joints.to_keypoints(jnp.array(q0), jnp.zeros(2))
        start = time.perf_counter()
        out = cldyn.simulate(system, x0, xd0, ts, dt0=DT, max_steps=steps + 2, **kwargs)
        jax.block_until_ready(out.x)
        seconds = time.perf_counter() - start
        phi = np.abs(np.asarray(jax.vmap(system.constraint)(out.x) - system.constraint(x0)[None, :])).max(
            axis=1
        )
        energy = np.asarray(jax.vmap(system.energy)(out.x, out.xd))
        e0 = float(system.energy(x0, xd0))
        rel = np.abs(energy - e0) / (e0 - float(rest))
        tenth = max(1, rel.size // 10)
        rows.append(
            {
                "start_q": list(q0),
                "max_constraint_error": float(np.nanmax(phi)) if np.all(np.isfinite(phi)) else float("inf"),
                "max_relative_energy_error": float(np.nanmax(rel))
                if np.all(np.isfinite(rel))
                else float("inf"),
                "energy_error_first_tenth": float(np.nanmax(rel[:tenth])),
                "energy_error_last_tenth": float(np.nanmax(rel[-tenth:]))
                if np.all(np.isfinite(rel))
                else float("inf"),
                "seconds": seconds,
            }
        )
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=100_000)
    args = parser.parse_args()
    system, joints = cldyn.systems.acrobot(actuators=None)
    result = {
        "benchmark": "drift",
        "system": "cldyn.systems.acrobot (point masses)",
        "dt": DT,
        "steps": args.steps,
    }
    table = [
        f"# Constraint drift and energy error: acrobot, {args.steps} steps of dt {DT} s, float64",
        "",
        "| method | max constraint error | max relative energy error | energy error, first 10% | "
        "energy error, last 10% |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, kwargs in methods().items():
        rows = run(system, joints, args.steps, kwargs)
        summary = {
            "max_constraint_error": max(r["max_constraint_error"] for r in rows),
            "max_relative_energy_error": max(r["max_relative_energy_error"] for r in rows),
            "energy_error_first_tenth": max(r["energy_error_first_tenth"] for r in rows),
            "energy_error_last_tenth": max(r["energy_error_last_tenth"] for r in rows),
            "runs": rows,
        }
        result[name] = summary
        table.append(
            f"| {name} | {summary['max_constraint_error']:.2e} | "
            f"{summary['max_relative_energy_error']:.2e} | "
            f"{summary['energy_error_first_tenth']:.2e} | {summary['energy_error_last_tenth']:.2e} |"
        )
    table += [
        "",
        f"Starts (shoulder, elbow angles from hanging, at rest): {list(STARTS)}. Relative energy error: "
        "|E - E0| / (E0 - E_rest). Targets: Projection <= 1e-10 constraint error; RATTLE bounded energy "
        "error (no secular growth) <= 1e-3.",
        "",
    ]
    result["machine"] = machine()
    write("drift", result, "\n".join(table))
    print(f"wrote {RESULTS / 'drift.md'}", file=sys.stderr)


if __name__ == "__main__":
    main()
