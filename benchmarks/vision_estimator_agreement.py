"""Do independently trained estimators err alike? Their joint-angle errors on the same frames, and the energy
balance with the velocity noise of one estimator cancelled by another's.

`benchmarks/vision_energy_balance.py` finds the stock acrobot's damping from frames only within 25% on one
render seed of two: the estimators' error that is not a smooth function of the pose biases the balance, and
instrumental variables made of disjoint samples of the same estimator do not remove it. If that error were
each network's own, a second and a third estimator trained independently on the same frames would remove
it: the balance's velocity products made of estimator A's and B's velocities (`qd_A qd_B`: unbiased where
their errors are independent) and instruments of C's. A rendered frame is a fixed function of the pose, so
an estimator's error is one too; what is called noise here is its part of high order in the pose (finer
than the Fourier series of order `--warp-order` that stands for the smooth warp), such as the pixel grid
makes. This script measures, on the same runs as the energy balance (dm_control's stock acrobot and the
damping-free KeyCLD acrobot under KeyCLD's camera, `--runs` runs of `--frames` frames, render `--seed`):

- each estimator's joint-angle error against MuJoCo (sense and offset aligned), and the part of it left
  after the smooth warp;
- the correlation of that part, and of its change from frame to frame, between every two estimators;
- the energy balance (`vision_energy_balance.balance`, Fourier order 3) with the columns made of A's and
  B's velocities, by least squares and with instruments of C's, at Savitzky-Golay windows of 9, 15 and
  25 samples and at the window `cldyn.identify` would choose on A's keypoints; energy and work from A's
  learnt model, converted to N m s with the joules per model unit that the gears fix.

The three estimators (`--models`, in the order A, B, C) default to the committed structured acrobot
models: `acrobot-structured`, `acrobot-augmented` and `acrobot-augmented-seed2`. Writes
benchmarks/results/vision_estimator_agreement.json and .md (with a nonzero seed, `_seed<seed>`); prints
the JSON.

    MUJOCO_GL=egl python benchmarks/vision_estimator_agreement.py --seed 1   # about 12 min on 2 cores
"""

import argparse
import os
import pathlib
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, repo_path, write  # noqa: E402
from vision_energy_balance import (  # noqa: E402
    SOURCES,
    _estimated_joints,
    _filters,
    _high_order,
    _joules,
    _polarised,
    balance,
)

MODELS = tuple(
    RESULTS / "vision_models" / name
    for name in ("acrobot-structured", "acrobot-augmented", "acrobot-augmented-seed2")
)
WINDOWS = (9, 15, 25)


def _aligned(q, reference):
    """`q` with each joint's sense and whole turns matched to `reference`'s (conventions, not errors)."""
    import numpy as np

    q = q.copy()
    for j in range(q.shape[-1]):
        steps = np.diff(q[..., j], axis=1).ravel(), np.diff(reference[..., j], axis=1).ravel()
        if np.corrcoef(*steps)[0, 1] < 0:
            q[..., j] = -q[..., j]
        q[..., j] -= 2 * np.pi * np.round(np.mean(q[..., j] - reference[..., j]) / (2 * np.pi))
    return q


def _errors(q, truth, order: int):
    """The error against MuJoCo's angles (wrapped, its mean direction removed) and its part left after a
    Fourier series of `order` in the true angles (the smooth warp)."""
    import numpy as np

    error = np.angle(np.exp(1j * (q - truth)))
    error = np.angle(np.exp(1j * (error - np.angle(np.exp(1j * error).mean(axis=(0, 1))))))
    return error, _high_order(error, truth, order)[0]


def _balances(estimates, order: int) -> dict:
    """The energy balance with `qd_A qd_B` columns (least squares) and C's instruments, per filter."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from scipy.signal import savgol_filter

    q_all = [e["q"] for e in estimates]
    dynamics, structure, x, frames = (estimates[0][k] for k in ("dynamics", "structure", "x", "frames"))
    runs, samples, _ = x.shape
    joules = _joules(dynamics, structure, x, frames)
    controls = jnp.asarray(np.asarray(frames.u, dtype=float).reshape(-1, frames.u.shape[-1]))
    tangent = jax.vmap(lambda a, b: jax.jvp(structure.joint_map.forward, (a,), (b,)))
    energy_and_power = _polarised(dynamics)
    filters = _filters(x, frames.dt, WINDOWS)
    fits = {}
    for label, (window, degree) in filters.items():
        smooth = [savgol_filter(q, window, degree, axis=1) for q in q_all]
        velocity = [savgol_filter(q, window, degree, deriv=1, delta=frames.dt, axis=1) for q in q_all]
        position, va = tangent(jnp.asarray(smooth[0].reshape(-1, 2)), jnp.asarray(velocity[0].reshape(-1, 2)))
        _, vb = tangent(jnp.asarray(smooth[0].reshape(-1, 2)), jnp.asarray(velocity[1].reshape(-1, 2)))
        energy, power = (
            np.asarray(v).reshape(runs, samples) for v in energy_and_power(position, va, vb, controls)
        )
        common = (smooth[0], velocity[0], energy, power, frames.dt, order, window // 2)
        fits[label] = {}
        for name, instrument in (("A x B", None), ("A x B, instruments C", velocity[2])):
            fit = balance(*common, other=velocity[1], instrument=instrument)
            fits[label][name] = {
                "damping": (fit["damping"] * joules).tolist(),
                "interval": (fit["interval"] * joules).tolist(),
                "windows": fit["windows"],
                "columns": fit["columns"],
            }
    return {"joules_per_model_unit": float(joules), "fits": fits}


def _markdown(result: dict) -> str:
    lines = [
        "# Do independently trained estimators err alike?",
        "",
        f"{result['runs']} runs of {result['frames']} frames (render seed {result['seed']}) per scene. "
        "Estimators A, B, C: " + ", ".join(f"`{m}`" for m in result["models"]) + ". Error: the joint angle "
        "read from the estimator's keypoints against MuJoCo's (sense and offset aligned), RMS in rad; `high "
        f"order`: its part left after a Fourier series of order {result['warp_order']} in the true angles "
        "(the smooth warp); correlations of that part, and of its change from one frame to the next, "
        "between two estimators.",
        "",
        "| scene | estimator | error, shoulder / elbow | high order, shoulder / elbow |",
        "| --- | --- | --- | --- |",
    ]
    for data, case in result["cases"].items():
        for name, e in zip("ABC", case["estimators"]):
            lines.append(
                f"| {data} | {name} | {e['error_rms'][0]:.4f} / {e['error_rms'][1]:.4f} | "
                f"{e['high_order_rms'][0]:.4f} / {e['high_order_rms'][1]:.4f} |"
            )
    lines += [
        "",
        "| scene | estimators | correlation of the high-order error, shoulder / elbow | of its steps |",
        "| --- | --- | --- | --- |",
    ]
    for data, case in result["cases"].items():
        for pair, c in case["correlations"].items():
            lines.append(
                f"| {data} | {pair} | {c['error'][0]:.2f} / {c['error'][1]:.2f} | "
                f"{c['steps'][0]:.2f} / {c['steps'][1]:.2f} |"
            )
    lines += [
        "",
        "Energy balance (N m s, 95% bootstrap interval over runs) with the velocity products of A and B, "
        "by least squares and with C's instruments; energy and work from A's learnt model. Truth: 0.05 at "
        "both joints on the stock acrobot, 0 on the damping-free one.",
        "",
        "| scene | filter | fit | shoulder | elbow |",
        "| --- | --- | --- | --- | --- |",
    ]
    for data, case in result["cases"].items():
        truth = case["true_damping"]
        for label, fits in case["balance"]["fits"].items():
            for name, fit in fits.items():
                cells = []
                for j in range(2):
                    value, (low, high) = fit["damping"][j], fit["interval"][j]
                    off = f" ({100 * (value / truth - 1):+.0f}%)" if truth else ""
                    cells.append(f"{value:.4f} [{low:.4f}, {high:.4f}]{off}")
                lines.append(f"| {data} | {label} | {name} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=60)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0, help="seed of the rendered runs")
    parser.add_argument("--order", type=int, default=3, help="Fourier order of the energy balance's basis")
    parser.add_argument("--warp-order", type=int, default=4, help="Fourier order that stands for the warp")
    parser.add_argument(
        "--models", nargs=3, default=[str(m) for m in MODELS], help="estimators A, B, C (model directories)"
    )
    args = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import keyvision

    started = time.perf_counter()
    protocol = keyvision.RenderProtocol(
        runs=args.runs, validation_runs=min(10, args.runs - 1), frames=args.frames
    )
    loaded = [keyvision.load_model(directory) for directory in args.models]
    cases = {}
    for data, (source, truth) in SOURCES.items():
        rendered = keyvision.render(source, protocol=protocol, seed=args.seed, workers=1)
        true_q = np.asarray(rendered.extras["qpos"], dtype=float)
        estimates = []
        for model, spec in loaded:
            q, dynamics, structure, x, frames = _estimated_joints(model, spec, rendered)
            error, rest = _errors(_aligned(q, true_q), true_q, args.warp_order)
            if estimates:  # B's and C's velocities in A's conventions; A's angles stay its joint map's
                q = _aligned(q, estimates[0]["q"])
            estimates.append(
                {
                    "q": q,
                    "dynamics": dynamics,
                    "structure": structure,
                    "x": x,
                    "frames": frames,
                    "error": error,
                    "rest": rest,
                }
            )
        correlations = {}
        for a, b in ((0, 1), (0, 2), (1, 2)):
            ra, rb = estimates[a]["rest"], estimates[b]["rest"]
            da, db = np.diff(ra, axis=1), np.diff(rb, axis=1)
            correlations["ABC"[a] + "ABC"[b]] = {
                "error": [float(np.corrcoef(ra[..., j].ravel(), rb[..., j].ravel())[0, 1]) for j in range(2)],
                "steps": [float(np.corrcoef(da[..., j].ravel(), db[..., j].ravel())[0, 1]) for j in range(2)],
            }
        cases[data] = {
            "scene": source,
            "true_damping": truth,
            "estimators": [
                {
                    "error_rms": np.sqrt((e["error"] ** 2).mean(axis=(0, 1))).tolist(),
                    "high_order_rms": np.sqrt((e["rest"] ** 2).mean(axis=(0, 1))).tolist(),
                }
                for e in estimates
            ],
            "correlations": correlations,
            "balance": _balances(estimates, args.order),
        }
        print(f"{data}: {cases[data]['correlations']}", file=sys.stderr, flush=True)
    result = {
        "runs": args.runs,
        "frames": args.frames,
        "seed": args.seed,
        "order": args.order,
        "warp_order": args.warp_order,
        "models": [repo_path(m) for m in args.models],
        "cases": cases,
        "wall_s": time.perf_counter() - started,
        "machine": machine(),
    }
    name = "vision_estimator_agreement" + (f"_seed{args.seed}" if args.seed else "")
    write(name, result, _markdown(result))


if __name__ == "__main__":
    main()
