"""`cldyn demo`: the main job on an embedded default, with no arguments and no downloads.

MuJoCo plays reality: trajectories are recorded, with 1 mm position noise, from dm_control's stock
acrobot, whose joints carry a damping of 0.05 that the nominal model (the same MJCF through `from_mjcf`,
without `include`) does not declare. `cldyn identify` finds the residual, traces it to the missing
effect, adds it, refits, and reports the error before and after.
"""

import argparse
import pathlib
import time


def run_demo(
    out: "str | pathlib.Path" = "demo_output",
    *,
    scene: str = "acrobot",
    runs: int = 40,
    duration: float = 4.0,
    noise: float = 1e-3,
    seed: int = 0,
) -> dict:
    """Record, identify, report; returns the report as a dict (see `Identification.to_dict`).

    **Arguments:**

    - `out`: output directory: `measured.npz` (the recording) and `identify/` (report and plots).
    - `scene`: the MJCF to record from (the "measured" reality); its nominal model is the same MJCF
      without its passive effects.
    - `runs`, `duration`: recorded runs and their length in seconds (100 Hz samples, MuJoCo RK4 at
      2 ms), with KeyCLD's protocol of random initial states and constant random controls.
    - `noise`: position noise on the measured keypoints (m).
    - `seed`: seed of the recording and of the identification.
    """
    import jax

    jax.config.update("jax_enable_x64", True)
    from .mujoco import record
    from .mujoco._identify import identify_recording

    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    print(
        f"[1/3] recording {runs} runs x {duration:g} s of dm_control's {scene!r} (noise {1e3 * noise:g} mm)"
    )
    data = record(
        scene,
        runs=runs,
        duration=duration,
        dt=0.01,
        physics_dt=0.002,
        integrator="rk4",
        noise=noise,
        seed=seed,
        progress=True,
    )
    data.save(out / "measured.npz")
    print(f"[2/3] identifying what the nominal model of {scene!r} is missing")
    result = identify_recording(data, scene, seed=seed, progress=True)
    print("[3/3] report")
    report_dir = result.save(out / "identify")
    print(result.summary())
    print(f"wrote {out / 'measured.npz'}, {report_dir / 'report.json'}, {report_dir / 'report.md'},")
    print(f"      {report_dir / 'error_over_time.png'} and {report_dir / 'residual_vs_feature.png'}")
    print(f"done in {time.perf_counter() - started:.0f} s")
    return result.to_dict()


def _demo_command(args: argparse.Namespace) -> int:
    run_demo(args.out, runs=args.runs, duration=args.duration, noise=args.noise, seed=args.seed)
    return 0


def register(subparsers) -> None:
    """Add `cldyn demo`."""
    parser = subparsers.add_parser(
        "demo",
        help="find the damping that dm_control's acrobot declares and its nominal model lacks",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", default="demo_output", type=pathlib.Path, help="output directory")
    parser.add_argument("--runs", type=int, default=40, help="recorded runs (default 40)")
    parser.add_argument("--duration", type=float, default=4.0, help="seconds per run (default 4)")
    parser.add_argument("--noise", type=float, default=1e-3, help="position noise in metres (default 0.001)")
    parser.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    parser.set_defaults(run=_demo_command)
