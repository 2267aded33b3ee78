"""Finding missing physics on the KeyCLD scenes: the acceptance matrix of tests/test_identify_mujoco.py,
as a table (benchmarks/identify.py has the rate x noise x duration matrix on purpose-built mechanisms).

Effects injected one at a time into the KeyCLD pendulum, cart-pole and acrobot MJCFs (MuJoCo RK4 at
2 ms, 100 Hz samples, 20 runs of 3 s), identified against the nominal MJCF; plus 1 mm position noise
for damping, two effects at once, and effect-free data (10 seeds). Then dm_control's stock cart-poles,
rail limits active, recorded at their own 10 ms with 1 mm noise: the one-pole scene as it is (nothing to
find), and the two-pole scene (`cartpole/two_poles`) with damping injected on its second hinge. The
protocol and the cases are those of the tests (imported from tests/test_identify_mujoco.py, whose
`CASES` the tests run too).

Writes benchmarks/results/identify_keycld.json and identify_keycld.md; prints the JSON.

    python benchmarks/identify_keycld.py
"""

import os
import pathlib
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import jax
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
from _common import machine, write  # noqa: E402

jax.config.update("jax_enable_x64", True)

from test_identify_mujoco import CASES, TWO_POLES, TWO_POLES_DAMPING, _identify, _stock  # noqa: E402


def row(label, result, effect, where, truth):
    top = result.detected[0] if result.detected else None
    found = top is not None and (top.name, top.where) == (effect, where)
    return {
        "case": label,
        "truth": truth,
        "top": None if top is None else f"{top.name}[{top.where}]",
        "value": None if top is None else top.value,
        "ci": None if top is None else list(top.ci),
        "relative_error": None if top is None else abs(top.value - truth) / truth,
        "correct_top": bool(found),
        "others": [d.candidate.label for d in result.detected[1:]],
        "rollout_before_m": result.before.rollout_rmse_1s,
        "rollout_after_m": result.after.rollout_rmse_1s,
        "rollout_drop": result.before.rollout_rmse_1s / result.after.rollout_rmse_1s,
        "accel_drop": result.before.accel_rmse / result.after.accel_rmse,
        "warnings": list(result.warnings),
    }


def main():
    started = time.perf_counter()
    rows = []
    for index, (scene, effect, where, change, truth) in enumerate(CASES):
        springref = np.radians(change["joints"][where]["springref"]) if effect == "joint_spring" else None
        near = (where, springref) if springref is not None else None
        result = _identify(scene, change, index, near=near)
        rows.append(row(f"{scene} {effect} at {where}", result, effect, where, truth))
    for scene, where, damping in (
        ("keycld/pendulum", "hinge", 0.1),
        ("keycld/cartpole", "slider", 1.0),
        ("keycld/acrobot", "elbow", 0.1),
    ):
        result = _identify(scene, dict(joints={where: {"damping": damping}}), 31, noise=1e-3)
        rows.append(
            row(f"{scene} joint_damping at {where}, 1 mm noise", result, "joint_damping", where, damping)
        )
    negatives = []
    for seed in range(10):
        result = _identify("keycld/acrobot", {}, 100 + seed)
        negatives.append([d.candidate.label for d in result.detected])
    change = dict(joints={"elbow": {"damping": 0.1}, "shoulder": {"stiffness": 10.0, "springref": 20}})
    two = _identify("keycld/acrobot", change, 7, near=("shoulder", np.radians(20)))
    stock = _stock("cartpole", {}, 0)
    two_poles = _stock(TWO_POLES, dict(joints={"hinge_2": {"damping": TWO_POLES_DAMPING}}), 0)
    rows.append(
        row(
            f"{TWO_POLES} joint_damping at hinge_2, 1 mm noise",
            two_poles,
            "joint_damping",
            "hinge_2",
            TWO_POLES_DAMPING,
        )
    )
    table = [
        "# Finding missing physics: injected effects (MuJoCo as reality)",
        "",
        "| case | truth | top detection | value | 95% interval | error "
        "| rollout 1 s: before -> after | drop | other detections |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        ci = "-" if r["ci"] is None else f"[{r['ci'][0]:.4g}, {r['ci'][1]:.4g}]"
        value = "-" if r["value"] is None else f"{r['value']:.4g}"
        error = "-" if r["relative_error"] is None else f"{100 * r['relative_error']:.1f}%"
        top = (r["top"] or "nothing") + ("" if r["correct_top"] else " (wrong)")
        table.append(
            f"| {r['case']} | {r['truth']:g} | {top} | {value} | {ci} | {error} | "
            f"{1e3 * r['rollout_before_m']:.2f} -> {1e3 * r['rollout_after_m']:.3f} mm | "
            f"{r['rollout_drop']:.0f}x | {', '.join(r['others']) or '-'} |"
        )
    false = sum(bool(n) for n in negatives)
    table += [
        "",
        f"Effect-free data (KeyCLD acrobot, 10 seeds): something detected in {false} of 10 ({negatives}).",
        "",
        "Two effects at once (acrobot: damping 0.1 on the elbow, stiffness 10 with springref 20 deg on the "
        "shoulder): "
        + ", ".join(f"{d.candidate.label} = {d.value:.4g}" for d in two.detected)
        + f"; rollout {1e3 * two.before.rollout_rmse_1s:.2f} -> "
        f"{1e3 * two.after.rollout_rmse_1s:.3f} mm.",
        "",
        "dm_control's stock cart-pole (rail limits at +-1.8 m active, 10 ms, 1 mm noise), nothing injected: "
        f"{stock.outcome}"
        + "".join(f"; {d.candidate.label} = {d.value:.4g}" for d in stock.detected)
        + f"; rollout {1e3 * stock.before.rollout_rmse_1s:.2f} -> "
        f"{1e3 * stock.after.rollout_rmse_1s:.2f} mm. "
        + " ".join(w for w in stock.warnings if "limits" in w)
        + ". The two-pole row above (`cartpole/two_poles`, damping on hinge_2) is recorded the same way: "
        + " ".join(w for w in two_poles.warnings if "limits" in w)
        + ".",
        "",
    ]
    result = {
        "benchmark": "identify_keycld",
        "cases": rows,
        "effect_free_detections": negatives,
        "two_effects": [d.to_dict() for d in two.detected],
        "stock_cartpole": {
            "outcome": stock.outcome,
            "detected": [d.to_dict() for d in stock.detected],
            "rollout_before_m": stock.before.rollout_rmse_1s,
            "rollout_after_m": stock.after.rollout_rmse_1s,
            "warnings": list(stock.warnings),
        },
        "seconds": time.perf_counter() - started,
        "machine": machine(),
    }
    write("identify_keycld", result, "\n".join(table))


if __name__ == "__main__":
    main()
