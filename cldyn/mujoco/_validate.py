"""`validate`: simulate an MJCF scene in MuJoCo and its `from_mjcf` model in cldyn, and compare."""

import json
import os
import pathlib
import time
from collections.abc import Sequence

import diffrax
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from .._integrate import simulate
from .._misc import (
    VALIDATION_PLOT,
    VALIDATION_REPORT,
    atomic_save,
    atomic_write,
    check_positive,
    optional_import,
)
from .._progress import AbstractProgressMeter, NoProgressMeter
from ._bridge import from_mjcf
from ._record import _control_range, prepare, random_initial_states, simulate_mujoco
from ._scenes import load_model

PLOT_NAME = VALIDATION_PLOT
REPORT_NAME = VALIDATION_REPORT


def _plot(path: pathlib.Path, ts: np.ndarray, errors: np.ndarray, title: str) -> None:
    # matplotlib's object interface: no pyplot, so no global backend or figure registry is touched.
    figure = optional_import("matplotlib.figure", purpose="validate's plot").Figure(figsize=(7, 4))
    ax = figure.subplots()
    floor = np.finfo(float).eps
    for run in errors:
        ax.semilogy(ts, np.maximum(run, floor), color="tab:blue", alpha=0.35, linewidth=0.8)
    ax.semilogy(
        ts, np.maximum(errors.max(axis=0), floor), color="black", linewidth=1.6, label="max over runs"
    )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("keypoint position error (m)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right")
    figure.tight_layout()
    atomic_save(path, lambda temporary: figure.savefig(temporary, dpi=120))


def validate(
    mjcf: "str | os.PathLike",
    *,
    out: "str | os.PathLike | None" = None,
    include: Sequence[str] = (),
    keypoints: Sequence[str] | None = None,
    runs: int = 10,
    duration: float = 2.0,
    dt: float = 0.01,
    physics_dt: float = 1e-4,
    seed: int = 0,
    rtol: float = 1e-12,
    atol: float = 1e-12,
    control_range=None,
    joint_limits: bool = False,
    progress_meter: AbstractProgressMeter = NoProgressMeter(),
) -> dict:
    """Compare `from_mjcf`'s cldyn model with MuJoCo on random motions.

    MuJoCo (RK4 at `physics_dt`) and cldyn (`cldyn.simulate` with diffrax's Dopri8 at tolerances
    `rtol`, `atol`, float64, no stabilisation) start from the same random initial states (KeyCLD's:
    hinge angles U(-pi, pi), slide positions U(-1, 1), velocities U(-0.1, 0.1)) with the same random
    constant controls (uniform in the control range, nonzero in every run); the keypoint positions
    are compared every `dt`. Needs JAX's 64-bit mode (the `cldyn validate` command turns it on): the
    agreement it measures lies far below float32's resolution.

    **Arguments:**

    - `mjcf`: the scene (see `scene_xml`).
    - `out`: a directory for `validation.json` and the plot `keypoint_error.png`; nothing is
      written if `None`.
    - `include`, `keypoints`: passed to `from_mjcf`.
    - `runs`, `duration`, `dt`: the number of runs, their length and the comparison interval (s).
    - `physics_dt`: MuJoCo's RK4 step.
    - `seed`: seeds initial states and controls.
    - `rtol`, `atol`: cldyn's step-size controller tolerances.
    - `control_range`: as in `record`.
    - `joint_limits`: keep MuJoCo's joint limits; off by default, since `from_mjcf` does not model
      them.
    - `progress_meter`: reports MuJoCo's runs (e.g. `cldyn.TqdmProgressMeter()`).

    **Returns:** the report (also written to `validation.json`): `max_position_error` (m, over all
    runs, keypoints and times), `max_velocity_error` (m/s), `position_error_per_run`,
    `initial_map_error` (the `JointMap` against MuJoCo's keypoints at the initial states),
    `constraint_drift` (the largest `|Phi(x(t)) - Phi(x(0))|` of cldyn's solution),
    `mujoco_constraints_active` (whether MuJoCo applied any constraint force: a limit or a contact
    the model lacks), `duration` (s) and the settings.
    """
    if jax.dtypes.canonicalize_dtype(jnp.float64) != jnp.float64:
        raise ValueError(
            "validate compares cldyn with MuJoCo far below float32's resolution: turn on JAX's 64-bit "
            "mode before calling it (the `cldyn validate` command does)"
        )
    check_positive("runs", runs, integer=True)
    for name, value in (("duration", duration), ("dt", dt), ("physics_dt", physics_dt)):
        check_positive(name, value)
    started = time.perf_counter()
    bridge = from_mjcf(mjcf, keypoints=keypoints, include=include)
    system = bridge.system
    model, _, source = load_model(mjcf)
    if not joint_limits:
        model.jnt_limited[:] = 0
    model.opt.timestep = physics_dt
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    substeps = int(round(dt / physics_dt))
    if substeps < 1 or abs(substeps * physics_dt - dt) > 1e-9 * dt:
        raise ValueError(f"dt={dt} must be a whole multiple of physics_dt={physics_dt}")
    samples = int(round(duration / dt)) + 1
    _, plane, chosen = prepare(model, keypoints)

    initial_seed, control_seed = np.random.SeedSequence(seed).spawn(2)
    qpos0, qvel0 = random_initial_states(model, runs, np.random.default_rng(initial_seed))
    bounds = _control_range(model, control_range)
    controls = np.random.default_rng(control_seed).uniform(bounds[:, 0], bounds[:, 1], (runs, model.nu))
    reference = simulate_mujoco(
        model,
        chosen,
        plane,
        qpos0,
        qvel0,
        lambda r, s, t, q, v: controls[r],
        samples,
        substeps,
        progress_meter=progress_meter,
    )
    ts = jnp.asarray(np.arange(samples) * dt)
    x0 = jnp.asarray(reference["x_clean"][:, 0])
    xd0 = jnp.asarray(reference["xd"][:, 0])
    mapped = jax.vmap(bridge.joints.to_keypoints)(jnp.asarray(qpos0), jnp.asarray(qvel0))
    initial_map_error = float(max(jnp.max(jnp.abs(mapped[0] - x0)), jnp.max(jnp.abs(mapped[1] - xd0))))

    @jax.jit
    @jax.vmap
    def solve(x0, xd0, u):
        trajectory = simulate(
            system,
            x0,
            xd0,
            ts,
            control=u if system.num_inputs else None,
            solver=diffrax.Dopri8(),
            stabilisation=None,
            rtol=rtol,
            atol=atol,
            max_steps=1_000_000,
        )
        drift = jnp.zeros(())
        if system.constraint is not None:
            phi = jax.vmap(system.constraint)(trajectory.x)
            drift = jnp.max(jnp.abs(phi - phi[:1]))
        return trajectory.x, trajectory.xd, drift

    u = jnp.asarray(controls)
    x, xd, drift = solve(x0, xd0, u)
    d = 2
    position = np.linalg.norm((np.asarray(x) - reference["x_clean"]).reshape(runs, samples, -1, d), axis=-1)
    velocity = np.linalg.norm((np.asarray(xd) - reference["xd"]).reshape(runs, samples, -1, d), axis=-1)
    errors = position.max(axis=-1)
    report = {
        "mjcf": source,
        "include": list(bridge.include),
        "keypoints": list(bridge.keypoint_names),
        "runs": runs,
        "duration": float(duration),
        "dt": dt,
        "physics_dt": physics_dt,
        "mujoco_integrator": "RK4",
        "cldyn_solver": "Dopri8",
        "rtol": rtol,
        "atol": atol,
        "seed": seed,
        "joint_limits": joint_limits,
        "max_position_error": float(errors.max()),
        "max_velocity_error": float(velocity.max()),
        "position_error_per_run": [float(e) for e in errors.max(axis=1)],
        "initial_map_error": initial_map_error,
        "constraint_drift": float(np.max(np.asarray(drift))),
        "mujoco_constraints_active": bool(reference["constraint_rows"].any()),
        "wall_time": time.perf_counter() - started,
    }
    if out is not None:
        directory = pathlib.Path(out)
        atomic_write(directory / REPORT_NAME, json.dumps(report, indent=2) + "\n")
        include_text = f", include={list(bridge.include)}" if bridge.include else ""
        _plot(
            directory / PLOT_NAME,
            np.asarray(ts),
            errors,
            f"{source}{include_text}: cldyn vs MuJoCo (RK4, dt={physics_dt:g}), {runs} runs",
        )
    return report
