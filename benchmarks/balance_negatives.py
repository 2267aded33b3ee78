"""The energy balance on damping-free MuJoCo data: keypoint against joint smoothing, and what MuJoCo's own
integrator dissipates.

The KeyCLD acrobot (`keycld/acrobot`: no damping, both joints driven) recorded by MuJoCo in the protocol of
`keyvision.render` (`cldyn.mujoco.record`'s KeyCLD defaults: random states, one random constant control per
run, 20% of runs at zero), `--runs` runs of `--seconds` sampled every 10 ms, for each of `--seeds` seeds, at
two physics steps: the scene's own (RK4, 10 ms: what the rendered frames show) and 1 ms. Per seed and step:

- MuJoCo's total energy along each run, its own kinetic and potential energy less the constant torques'
  work (`-tau . q`, conserved without dissipation): the median and the largest loss over a run, relative
  to the run's largest energy, and the viscous elbow damping that would dissipate the total loss of all
  runs (`-sum dE / sum int qd_elbow^2`, N m s);
- `cldyn.energy_balance` on MuJoCo's exact keypoints against the exact model (`from_mjcf`), the
  velocities smoothed in keypoint coordinates and in joint coordinates (`joints=`), and again through
  `--noise` metres of white noise: each joint's damping with its 95% interval (N m s), and whether the
  interval lies above zero (a detection, false here).

Writes benchmarks/results/balance_negatives.{json,md} and prints the JSON.

    MUJOCO_GL=egl python benchmarks/balance_negatives.py   # about 6 min on 2 cores
"""

import argparse
import sys
import time

import jax
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import machine, write  # noqa: E402

jax.config.update("jax_enable_x64", True)

import cldyn  # noqa: E402

SCENE = "keycld/acrobot"
STEPS = {"RK4, 10 ms (the scene's)": 0.01, "RK4, 1 ms": 0.001}


def _energy_loss(xml: str, data) -> dict:
    """MuJoCo's energy less the constant torques' work along each run."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(xml)
    model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    state = mujoco.MjData(model)
    qpos, qvel = data.extras["qpos"], data.extras["qvel"]
    energy = np.empty(qpos.shape[:2])
    for r, t in np.ndindex(*energy.shape):
        state.qpos[:], state.qvel[:] = qpos[r, t], qvel[r, t]
        mujoco.mj_forward(model, state)
        energy[r, t] = state.energy.sum()
    joints = model.actuator_trnid[:, 0]
    torque = np.asarray(data.u) * model.actuator_gear[:, 0]
    total = energy - np.einsum("rtk,rtk->rt", torque, qpos[..., model.jnt_qposadr[joints]])
    loss = total[:, -1] - total[:, 0]
    relative = -loss / np.abs(energy).max(axis=1)
    squared = (qvel[..., 1] ** 2).sum(axis=1) * float(data.dt)
    return {
        "median_loss": float(np.median(relative)),
        "largest_loss": float(relative.max()),
        "elbow_damping_equivalent": float(-loss.sum() / squared.sum()),
    }


def _balance(bridge, data, joints) -> dict:
    coordinates = dict(zip(bridge.joint_names, bridge.joint_coordinates))
    found = cldyn.energy_balance(bridge.system, data, joint_coordinates=coordinates, joints=joints)
    return {
        "damping": [float(v) for v in found.damping],
        "interval": [[float(a), float(b)] for a, b in found.interval],
        "detected": list(found.detected),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--noise", type=float, default=0.001)
    args = parser.parse_args()
    from cldyn.mujoco import from_mjcf, record, scene_xml

    xml, bridge = scene_xml(SCENE), from_mjcf(SCENE)
    started = time.perf_counter()
    rows = []
    for seed in range(args.seeds):
        for step_name, step in STEPS.items():
            data = record(
                xml,
                runs=args.runs,
                duration=args.seconds,
                dt=0.01,
                physics_dt=step,
                integrator="rk4",
                seed=seed,
            )
            noisy = data.x + args.noise * np.random.default_rng(seed).standard_normal(data.x.shape)
            row = {"seed": seed, "physics": step_name, "energy": _energy_loss(xml, data)}
            for label, x in (("exact", data.x), (f"noise {args.noise:g} m", noisy)):
                sequences = cldyn.Sequences(x, data.u, data.dt)
                for space, joints in (("keypoints", None), ("joints", bridge.joints)):
                    row[f"{label}, {space}"] = _balance(bridge, sequences, joints)
            rows.append(row)
            print(f"seed {seed}, {step_name}: done ({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    columns = [k for k in rows[0] if k not in ("seed", "physics", "energy")]
    result = {
        "machine": machine(),
        "scene": SCENE,
        "runs": args.runs,
        "seconds": args.seconds,
        "rows": rows,
        "detections": {
            step_name: {
                c: sum(bool(r[c]["detected"]) for r in rows if r["physics"] == step_name) for c in columns
            }
            for step_name in STEPS
        },
        "seconds_taken": round(time.perf_counter() - started, 1),
    }
    lines = [
        "# The energy balance on damping-free MuJoCo data (`benchmarks/balance_negatives.py`)",
        "",
        f"`{SCENE}` (no damping), {args.runs} runs of {args.seconds:g} s per seed in "
        "`keyvision.render`'s protocol, sampled every 10 ms; MuJoCo's RK4 at the scene's 10 ms step "
        "and at 1 ms. Energy: MuJoCo's energy less the constant torques' work, its loss over a run "
        "relative to the run's largest energy (median and largest over runs), and the elbow damping "
        "that would dissipate the total (N m s). Then `cldyn.energy_balance` against the exact model "
        "on MuJoCo's keypoints, exact and noisy, the velocities smoothed through the keypoints or "
        "through the joints (`joints=`): shoulder and elbow damping in N m s with 95% intervals, `*` "
        "where the interval lies above zero (a detection; the truth is none).",
        "",
        "| seed | physics | energy lost (median / largest) | elbow damping equivalent | "
        + " | ".join(columns)
        + " |",
        "| --- | --- | --- | --- | " + " | ".join("---" for _ in columns) + " |",
    ]

    def cell(found):
        return ", ".join(
            f"{v:.4f} [{a:.4f}, {b:.4f}]" + ("*" if a > 0 else "")
            for v, (a, b) in zip(found["damping"], found["interval"])
        )

    for r in rows:
        e = r["energy"]
        lines.append(
            f"| {r['seed']} | {r['physics']} | {e['median_loss']:.2%} / {e['largest_loss']:.2%} | "
            f"{e['elbow_damping_equivalent']:.4f} | " + " | ".join(cell(r[c]) for c in columns) + " |"
        )
    lines += ["", "Seeds with a detection (of " + str(args.seeds) + "):", ""]
    for step_name, counts in result["detections"].items():
        lines.append(f"- {step_name}: " + ", ".join(f"{c}: {n}" for c, n in counts.items()))
    write("balance_negatives", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
