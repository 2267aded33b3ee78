"""Keypoint feedback control of MuJoCo scenes: `closed_loop`, `swing_up` and `cldyn control`."""

import argparse
import json
import os
import pathlib
import time
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._control import EnergyShaping
from ._bridge import from_mjcf
from ._record import Recording, record


def closed_loop(
    mjcf: "str | os.PathLike",
    controller: Callable,
    *,
    runs: int,
    duration: float,
    initial,
    dt: float = 0.01,
    physics_dt: float = 0.002,
    origin: Sequence[float] | None = None,
    keypoints: Sequence[str] | None = None,
    seed: int = 0,
    progress: bool = False,
) -> Recording:
    """Run a keypoint feedback policy on a MuJoCo scene.

    At every sample MuJoCo's state is read as keypoints (positions and velocities of the scene's
    keypoints, through `from_mjcf`'s exact map), the policy `u = controller(t, x, xd)` is evaluated
    (jit-compiled) and held until the next sample while MuJoCo steps with RK4.

    **Arguments:**

    - `mjcf`: the scene (path, XML string, suite name or `"keycld/<name>"`).
    - `controller`: a policy `u(t, x, xd)` in keypoint coordinates, e.g. `cldyn.EnergyShaping`.
    - `runs`, `duration`: number of runs and seconds per run.
    - `initial`: `(qpos, qvel)` arrays of shape `(runs, nq)` and `(runs, nv)`.
    - `dt`, `physics_dt`: control period and MuJoCo's step.
    - `origin`: a point `(2,)` subtracted from every keypoint before the policy sees it (models
      learned on `keycld_dataset`, whose keypoints are relative to the scene's pivot).
    - `keypoints`: site names, if not the scene's default keypoints.
    - `seed`, `progress`: as in `record`.

    **Returns:** the `Recording` of the closed-loop runs.
    """
    bridge = from_mjcf(mjcf, keypoints=keypoints)
    shift = jnp.zeros(2) if origin is None else jnp.asarray(origin, dtype=float)
    count = len(bridge.keypoint_names)

    @jax.jit
    def policy(t, qpos, qvel):
        x, xd = bridge.joints.to_keypoints(qpos, qvel)
        return controller(t, x - jnp.tile(shift, count), xd)

    def control(t, qpos, qvel):
        return np.asarray(policy(jnp.asarray(t, dtype=float), jnp.asarray(qpos), jnp.asarray(qvel)))

    return record(
        mjcf,
        runs=runs,
        duration=duration,
        dt=dt,
        physics_dt=physics_dt,
        integrator="rk4",
        initial=initial,
        control=control,
        keypoints=keypoints,
        seed=seed,
        progress=progress,
    )


def _postures(bridge) -> tuple[np.ndarray, np.ndarray]:
    """`(hanging, upright)` joint positions: every hinge at the angle that puts the keypoints lowest or
    highest (slides at zero), found from the geometry rather than from a joint convention."""
    hinges = [j for j, c in enumerate(bridge.joint_coordinates) if "Slider" not in type(c).__name__]
    best = {}
    for angles in (
        np.array(np.meshgrid(*([[0.0, np.pi]] * len(hinges)), indexing="ij")).reshape(len(hinges), -1).T
    ):
        q = np.zeros(len(bridge.joint_names))
        q[hinges] = angles
        height = float(np.sum(np.asarray(bridge.joints.keypoints(jnp.asarray(q))).reshape(-1, 2)[:, 1]))
        best.setdefault("low", (height, q))
        best.setdefault("high", (height, q))
        if height < best["low"][0]:
            best["low"] = (height, q)
        if height > best["high"][0]:
            best["high"] = (height, q)
    return best["low"][1], best["high"][1]


def swing_up(
    mjcf: "str | os.PathLike",
    *,
    kp: float = 5.0,
    kd: float = 2.0,
    damping: str = "keypoint",
    system=None,
    origin: Sequence[float] | None = None,
    runs: int = 20,
    duration: float = 10.0,
    tolerance: float = 0.05,
    perturbation: float = 0.2,
    seed: int = 0,
    progress: bool = False,
) -> dict:
    """Energy-shaping swing-up (eq. 32) of a fully actuated MuJoCo scene, from hanging to upright.

    Each run starts near the hanging posture (joint angles within `perturbation` rad of it, velocities
    within 0.1) and is controlled by `EnergyShaping(system, x_upright, kp, kd)` built on `system` (the
    analytic `from_mjcf` model by default, or a learned one). A run succeeds when every keypoint is within
    `tolerance` of the upright target over the last 0.5 s before `duration`.

    **Arguments:**

    - `mjcf`: the scene.
    - `kp`, `kd`, `damping`: the controller's gains and damping form (see `EnergyShaping`).
    - `system`: the model the controller uses; `from_mjcf(mjcf).system` by default.
    - `origin`: subtracted from the keypoints the model sees (see `closed_loop`).
    - `runs`, `duration`, `tolerance`, `perturbation`, `seed`: the protocol.
    - `progress`: show MuJoCo's progress.

    **Returns:** a dict with the success rate, per-run final errors and times to reach the tolerance,
    the error curves (`ts`, `errors` of shape `(runs, T)`) and the recording.
    """
    bridge = from_mjcf(mjcf)
    hanging, upright = _postures(bridge)
    shift = np.zeros(2) if origin is None else np.asarray(origin, dtype=float)
    target_world = np.asarray(bridge.joints.keypoints(jnp.asarray(upright)))
    model = bridge.system if system is None else system
    target = jnp.asarray(target_world - np.tile(shift, len(bridge.keypoint_names)), dtype=float)
    controller = EnergyShaping(model, target.astype(model.mass.matrix().dtype), kp, kd, damping=damping)
    rng = np.random.default_rng(seed)
    qpos = hanging + rng.uniform(-perturbation, perturbation, size=(runs, hanging.size))
    qvel = rng.uniform(-0.1, 0.1, size=qpos.shape)
    data = closed_loop(
        mjcf,
        controller,
        runs=runs,
        duration=duration,
        initial=(qpos, qvel),
        origin=origin,
        seed=seed,
        progress=progress,
    )
    x = data.x_clean.reshape(runs, data.x.shape[1], -1, 2)
    errors = np.linalg.norm(x - target_world.reshape(1, 1, -1, 2), axis=-1).max(axis=-1)
    window = max(1, int(round(0.5 / data.dt)))
    success = errors[:, -window:].max(axis=1) < tolerance
    reached = [float(data.time[np.argmax(e < tolerance)]) if (e < tolerance).any() else None for e in errors]
    return {
        "scene": str(mjcf),
        "kp": kp,
        "kd": kd,
        "damping": damping,
        "runs": runs,
        "duration": duration,
        "tolerance": tolerance,
        "success_rate": float(success.mean()),
        "success": success.tolist(),
        "final_error": errors[:, -1].tolist(),
        "time_to_tolerance": reached,
        "max_abs_control": float(np.abs(data.u).max()),
        "ts": data.time,
        "errors": errors,
        "recording": data,
    }


def plot_swing_up(results: Sequence[dict], path: "str | os.PathLike") -> None:
    """Keypoint error to the upright target over time, one panel per result of `swing_up`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.4), squeeze=False)
    for ax, result in zip(axes[0], results):
        for e in result["errors"]:
            ax.plot(result["ts"], e, lw=0.8, alpha=0.6)
        ax.axhline(result["tolerance"], color="k", ls="--", lw=1)
        ax.set_yscale("log")
        ax.set_title(
            f"{result['scene']} ({result['damping']}): {100 * result['success_rate']:.0f}% succeed",
            fontsize=9,
        )
        ax.set_xlabel("time (s)")
        ax.set_ylabel("max keypoint error to upright (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _control_command(args: argparse.Namespace) -> int:
    jax.config.update("jax_enable_x64", True)
    system, origin = None, None
    if args.model is not None:
        from .._learn_cli import load_fitted
        from ._datasets import keycld_origin

        system, spec = load_fitted(args.model)
        system = jax.tree_util.tree_map(lambda a: a.astype(float) if hasattr(a, "astype") else a, system)
        origin = keycld_origin(args.mjcf.removeprefix("keycld/")) if args.mjcf.startswith("keycld/") else None
    started = time.perf_counter()
    result = swing_up(
        args.mjcf,
        kp=args.kp,
        kd=args.kd,
        damping=args.damping,
        system=system,
        origin=origin,
        runs=args.runs,
        duration=args.duration,
        seed=args.seed,
        progress=True,
    )
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {k: v for k, v in result.items() if k not in ("ts", "errors", "recording")}
    summary["model"] = str(args.model) if args.model else "from_mjcf (analytic)"
    summary["seconds"] = time.perf_counter() - started
    (out / "control.json").write_text(json.dumps(summary, indent=2))
    plot_swing_up([result], out / "control.png")
    print(
        f"{args.mjcf}: {100 * result['success_rate']:.0f}% of {args.runs} runs within "
        f"{result['tolerance']} m of upright after {args.duration:g} s; "
        f"wrote {out / 'control.json'} and {out / 'control.png'}"
    )
    return 0


def register(subparsers) -> None:
    """Add `cldyn control`."""
    parser = subparsers.add_parser(
        "control",
        help="energy-shaping swing-up of a MuJoCo scene with an analytic or learned model",
        description="Swing a fully actuated scene from hanging to upright with cldyn.EnergyShaping (eq. 32) "
        "as a keypoint feedback policy on MuJoCo, over random starts; report the success rate.",
    )
    parser.add_argument(
        "--mjcf", required=True, help="scene: file, suite name or keycld/<pendulum|cartpole|acrobot>"
    )
    parser.add_argument("--out", required=True, help="output directory for control.json and control.png")
    parser.add_argument(
        "--model", default=None, help="a `cldyn fit` output directory (default: the analytic model)"
    )
    parser.add_argument("--kp", type=float, default=5.0, help="stiffness of the shaped potential (default 5)")
    parser.add_argument("--kd", type=float, default=2.0, help="damping gain (default 2)")
    parser.add_argument("--damping", choices=("keypoint", "output"), default="keypoint", help="damping form")
    parser.add_argument("--runs", type=int, default=20, help="random starts (default 20)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per run (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the starts")
    parser.set_defaults(run=_control_command)
