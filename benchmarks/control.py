"""Energy-shaping swing-up in MuJoCo with the paper's gains (kp = 5, kd = 2).

For the fully actuated KeyCLD pendulum, cart-pole and acrobot, 20 random starts near hanging each,
controlled for 10 s by `cldyn.EnergyShaping` built on the analytic model (`from_mjcf` of the scene) and
run as a keypoint feedback policy on MuJoCo (RK4, 2 ms, control at 100 Hz). Success: every keypoint
within 0.05 m of the upright target over the last 0.5 s. Both damping forms: `keypoint` (the default,
`-kd xd` matched through `(g^T g)^-1 g^T`) and `output` (eq. 32 as printed, `-kd g^T xd`). Then the
same (keypoint damping) with the controller built on the learned KeyCLD models of
`benchmarks/learning.py`, where they have been fitted.

Writes benchmarks/results/control.json, control.md and control.png; prints the JSON.

    python benchmarks/control.py
"""

import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import jax

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import RESULTS, machine, write  # noqa: E402

jax.config.update("jax_enable_x64", True)

from cldyn.mujoco import plot_swing_up, swing_up  # noqa: E402

SCENES = ("keycld/pendulum", "keycld/cartpole", "keycld/acrobot")


def main():
    result = {"benchmark": "control", "kp": 5.0, "kd": 2.0, "runs": 20, "duration": 10.0, "tolerance": 0.05}
    table = [
        "# Energy-shaping swing-up in MuJoCo (kp = 5, kd = 2, analytic model)",
        "",
        "| scene | damping | success | median time to 0.05 m (s) | max final error (m) |",
        "| --- | --- | --- | --- | --- |",
    ]
    plotted = []
    for damping in ("keypoint", "output"):
        for scene in SCENES:
            r = swing_up(scene, damping=damping, runs=20, duration=10.0, seed=0)
            times = sorted(t for t in r["time_to_tolerance"] if t is not None)
            median = times[len(times) // 2] if times else None
            key = f"{scene} / {damping}"
            result[key] = {k: v for k, v in r.items() if k not in ("ts", "errors", "recording")}
            table.append(
                f"| {scene} | {damping} | {100 * r['success_rate']:.0f}% | "
                f"{'-' if median is None else f'{median:.1f}'} | {max(r['final_error']):.3g} |"
            )
            if damping == "keypoint":
                plotted.append(r)
    plot_swing_up(plotted, RESULTS / "control.png")
    table += ["", "Plot: `control.png` (keypoint damping).", ""]
    table += _learned(result)
    result["machine"] = machine()
    write("control", result, "\n".join(table))


# -- learned models (issue 5): the same swing-up with the controller built on the KeyCLD models that
# benchmarks/learning.py fitted to MuJoCo data; skipped for models that have not been fitted ---------


def _learned(result: dict) -> list[str]:
    import _learned as learned

    from cldyn.mujoco import from_mjcf

    rows, plotted = [], []
    for scene in SCENES:
        name = scene.removeprefix("keycld/")
        for model_name in ("keycld", "keycld-coupled"):
            loaded = learned.load(name, model_name)
            if loaded is None:
                continue
            model, origin = loaded
            r = swing_up(scene, system=model, origin=origin, runs=20, duration=10.0, seed=0)
            a = learned.scale(model, from_mjcf(scene))
            times = sorted(t for t in r["time_to_tolerance"] if t is not None)
            median = times[len(times) // 2] if times else None
            result[f"{scene} / learned {model_name}"] = dict(
                {k: v for k, v in r.items() if k not in ("ts", "errors", "recording")}, model_scale=a
            )
            rows.append(
                f"| {scene} | {model_name} | {100 * r['success_rate']:.0f}% | "
                f"{'-' if median is None else f'{median:.1f}'} | {max(r['final_error']):.3g} | {a:.2f} |"
            )
            if model_name == "keycld":
                plotted.append(dict(r, scene=f"{scene}, learned KeyCLD"))
    if not rows:
        return []
    plot_swing_up(plotted, RESULTS / "control_learned.png")
    return [
        "## Learned models (benchmarks/learning.py), kp = 5, kd = 2, keypoint damping",
        "",
        "`keycld`: the paper's model (point masses); `keycld-coupled`: coupled masses. The scale `a` is",
        "the learned mass matrix over the true one on the tangent space: a learned model is defined up to",
        "a common factor of mass, potential and input matrix, and the controller then acts with gains",
        "`kp / a`, `kd / a`.",
        "",
        "| scene | model | success | median time to 0.05 m (s) | max final error (m) | scale a |",
        "| --- | --- | --- | --- | --- | --- |",
        *rows,
        "",
        "Plot: `control_learned.png` (learned KeyCLD).",
        "",
    ]


if __name__ == "__main__":
    main()
