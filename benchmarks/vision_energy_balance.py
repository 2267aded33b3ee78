"""Can the stock acrobot's damping be seen from frames at all? An energy balance that no conservative model
error can fake, measured on MuJoCo's states and on the learnt acrobot's estimates from frames.

`keyvision.identify` finds no damping on dm_control's stock acrobot (0.05 N m s at both joints) because the
learnt model's force errors are some twenty times the damping's force (docs/images.md). This diagnostic asks
whether a test that is blind to those errors would do better. Along a run, energy changes only by the work of
the controls and of the dissipation, so over any window `[a, b]`

    E(b) - E(a) - W_ab = -sum_j c_j int_a^b qd_j^2 dt,

and a model whose inertia or potential is wrong makes an error in `E` only at the window's two ends, never
one that grows with the window. The unknown error is written in a basis in which any energy of a chain of
two hinges lies: `V(q)` and the three entries of `M(q)` (times the velocity products) as Fourier series in
the joint angles up to order `--order`. Windows start and end every 10 samples of each run; the damping
`c_j` and the basis coefficients are one least-squares fit over all of them, with a bootstrap over runs for
the 95% intervals.

The same runs of two scenes (dm_control's stock acrobot and the damping-free KeyCLD acrobot, both under
KeyCLD's camera, `--runs` runs of `--frames` frames rendered with `--seed`), measured five ways:

- `state`: MuJoCo's joint positions and velocities in MuJoCo's units, `W` from the gear and the control as
  MuJoCo applied it: what the test gives when the measurement is exact;
- velocities from angles by a Savitzky-Golay filter, for each window of `--windows` (degree 3) and for
  the window and degree that `cldyn.identify` would choose on the estimated keypoints; `W` MuJoCo's own:
  - `filtered`: MuJoCo's angles as they are, so only the filter errs;
  - `+ warp`: MuJoCo's angles warped by the estimator's error that is a fixed function of the pose (a
    Fourier fit of order 4 in the true angles, per joint);
  - `+ noise`: MuJoCo's angles plus white noise of the RMS of the estimator's remaining error;
  - `frames`: the joints of the keypoints that the learnt model's estimator reads from the frames, with
    `E` and `W` from the learnt model, converted to N m s with the joules per model unit that the
    scene's gears fix (`keyvision.identify`'s conversion).
- and three of those again by instrumental variables (`filtered`, `+ noise`, `frames`, each
  `instrumented`): noise in the velocities makes the fit's columns noisy, and least squares on noisy
  columns is biased (errors in variables). Three velocity estimates from disjoint samples of each
  filter's window (the offsets 0, 1 and 2 modulo 3) have independent noises where the angles' noise is
  white: the columns are made of the first two (each velocity product symmetric in them, the learnt
  energy polarised to match), the instruments of the third.
- and the `frames` fits again with the basis of an error of the learnt input map (`input basis`): the
  work `W` of the `frames` rows is the learnt model's, `int u^T B(x)^T xd`, and a wrong `B` errs in it by
  `int u^T dB(q)^T qd`, which is linear in the velocity and grows with the window like the dissipation
  does. Columns `int u_k f_i(q) qd_j` (every control, joint and Fourier term of `--order`) hold any
  smooth `dB`; the rows on MuJoCo's work need none.

Each of `--models` (by default the two committed acrobot models: KeyCLD's, and the structured one of
docs/images.md's "Control from frames") is measured on the same runs, rendered through the camera the
model was trained on (its `keyvision.json`'s `data.supersample`; `--supersample` for another). Also
reported: the estimator's joint-angle error against MuJoCo (sign and offset aligned) and the part of it
that is not a function of the pose. Writes benchmarks/results/vision_energy_balance.{json,md} (with a
nonzero seed, `vision_energy_balance_seed<seed>.{json,md}`; `--name` for another) and prints the JSON.

    MUJOCO_GL=egl python benchmarks/vision_energy_balance.py   # about 35 min on 2 cores
    MUJOCO_GL=egl python benchmarks/vision_energy_balance.py --seed 1 \
        --models benchmarks/results/vision_models/acrobot-augmented --name vision_energy_balance_aug_seed1
"""

import argparse
import os
import pathlib
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, VISION_MODELS, machine, repo_path, write  # noqa: E402

SOURCES = {"stock": ("keycld/acrobot:stock", 0.05), "damping-free": ("keycld/acrobot", 0.0)}
JOINTS = ("shoulder", "elbow")
# the fits on the estimator's joints: least squares and instrumental variables, each also with the basis of an
# error of the learnt input map (`_input_columns`)
FRAME_SOURCES = ("frames", "frames, input basis", "frames, instrumented", "frames, instrumented, input basis")
# the committed acrobot models: KeyCLD's, and the structured one of "Control from frames" (docs/images.md)
MODELS = (VISION_MODELS["acrobot"], RESULTS / "vision_models" / "acrobot-structured")


def _fourier(q, order: int):
    """`1, cos(m q1 + n q2), sin(...)` for `0 < |m| + |n| <= order` (one of each +-pair): `(..., F)`."""
    import numpy as np

    columns = [np.ones(q.shape[:-1])]
    for m in range(order + 1):
        for n in range(-order, order + 1):
            if (m == 0 and n <= 0) or m + abs(n) > order:
                continue
            angle = m * q[..., 0] + n * q[..., 1]
            columns += [np.cos(angle), np.sin(angle)]
    return np.stack(columns, -1)


def _high_order(error, truth, order: int) -> tuple:
    """`(rest, warp)`: the joint-angle errors `error` `(runs, samples, J)` split into a Fourier series of
    `order` in the true angles `truth` (the smooth warp, least squares per joint) and what it leaves."""
    import numpy as np

    basis = _fourier(truth.reshape(-1, truth.shape[-1]), order)
    coefficients, *_ = np.linalg.lstsq(basis, error.reshape(-1, error.shape[-1]), rcond=None)
    warp = (basis @ coefficients).reshape(error.shape)
    return error - warp, warp


def _cumulative(f, dt: float):
    """`int_0^t f` at every sample, along axis 1, of the cubic spline through the samples."""
    import numpy as np
    from scipy.interpolate import CubicSpline

    t = dt * np.arange(f.shape[1])
    return CubicSpline(t, f, axis=1).antiderivative()(t)


def _disjoint(q, window: int, degree: int, dt: float, ends) -> list:
    """Three velocity estimates from disjoint samples of each window of `window` samples: from the offsets
    that are 0, 1 and 2 modulo 3 (each the derivative at 0 of a polynomial of `degree`, lower where its
    samples are fewer). Where the angles' noise is white, the three estimates' noises are independent.
    `ends` fills the first and last `window // 2` samples."""
    import numpy as np

    half, samples = window // 2, q.shape[1]
    estimates = []
    for remainder in range(3):
        offsets = np.array([o for o in range(-half, half + 1) if o % 3 == remainder], dtype=float)
        powers = offsets[:, None] ** np.arange(min(degree, offsets.size - 1) + 1)
        weights = np.linalg.pinv(powers)[1] / dt
        qd = np.array(ends, dtype=float)
        qd[:, half : samples - half] = sum(
            w * q[:, half + int(o) : samples - half + int(o)] for o, w in zip(offsets, weights)
        )
        estimates.append(qd)
    return estimates


def _differences(trig, qd, other, dt: float, first, last):
    """The fit's columns over the windows `[first, last]`: `-int qd_j other_j` and minus the change of the
    basis (the potential's Fourier terms `trig`, and each symmetric velocity product times them)."""
    import numpy as np

    basis = [trig[..., 1:]]  # the potential (its constant drops out of every difference)
    for i, j in ((0, 0), (0, 1), (1, 1)):
        product = (qd[..., i] * other[..., j] + other[..., i] * qd[..., j]) / 2
        basis.append(product[..., None] * trig)
    basis = np.concatenate(basis, -1)
    dissipated = _cumulative(qd * other, dt)
    return np.concatenate(
        [-(dissipated[:, last] - dissipated[:, first]), -(basis[:, last] - basis[:, first])], -1
    )


def _input_columns(trig, velocity, controls, dt: float, first, last):
    """Columns for an error of the input map: `-int u_k f_i(q) qd_j` over each window, for every control
    `k`, joint `j` and Fourier term `f_i`. The work that a wrong input matrix `B + dB(q)` reports is off
    by `int u^T dB(q)^T qd`, linear in the velocity; any smooth `dB` lies in this basis."""
    import numpy as np

    columns = []
    for k in range(controls.shape[-1]):
        for j in range(velocity.shape[-1]):
            flow = _cumulative(controls[..., k, None] * trig * velocity[..., j, None], dt)
            columns.append(-(flow[:, last] - flow[:, first]))
    return np.concatenate(columns, -1)


def _without(columns, direction):
    """`columns` `(runs, windows, C)` less their least-squares projection on `direction` `(..., 1)`."""
    import numpy as np

    share = np.sum(direction * columns, axis=(0, 1)) / max(float(np.sum(direction**2)), 1e-300)
    return columns - direction * share


def balance(
    q,
    qd,
    energy,
    power,
    dt: float,
    order: int,
    edge: int,
    seed: int = 0,
    other=None,
    instrument=None,
    controls=None,
) -> dict:
    """Fit `E(b) - E(a) - W_ab = -sum_j c_j int qd_j^2 - [basis](b) + [basis](a)` over all windows, by least
    squares. With `other` and `instrument` (`_disjoint`'s second and third estimates), by instrumental
    variables: the velocity products are those of `qd` and `other` (`energy` must be made the same way) and
    the instruments are the same columns made of `instrument` alone. Noise in the velocities makes the
    columns noisy, which biases least squares (errors in variables); the instruments' noise is independent
    of theirs, so it does not. With `controls` (`(runs, samples, l)`), the fit also takes an error of the
    input map through which `power` was computed (`_input_columns`)."""
    import numpy as np

    runs, samples = q.shape[:2]
    points = np.arange(edge, samples - edge, 10)
    first, last = (points[i] for i in np.triu_indices(len(points), 1))
    work = _cumulative(power, dt)
    y = energy[:, last] - energy[:, first] - (work[:, last] - work[:, first])
    trig = _fourier(q, order)
    a = _differences(trig, qd, qd if other is None else other, dt, first, last)
    if controls is not None:
        mean = qd if other is None else (qd + other) / 2
        inputs = _input_columns(trig, mean, controls, dt, first, last)
        # the basis holds the reported work itself (a gear error), and with it every rescaling of the
        # balance: E, W and the dissipation times any factor fit as well, so damping 0 does too. The
        # gears fix that scale (the model's units are converted with them), so the work's own
        # direction is taken out of the basis: it holds errors in the input map's shape, not its size.
        reported = (work[:, last] - work[:, first])[..., None]
        a = np.concatenate([a, _without(inputs, reported)], -1)
    norm = np.linalg.norm(a.reshape(-1, a.shape[-1]), axis=0) + 1e-300
    if instrument is not None:
        z = _differences(trig, instrument, instrument, dt, first, last)
        if controls is not None:
            inputs = _input_columns(trig, instrument, controls, dt, first, last)
            z = np.concatenate([z, _without(inputs, reported)], -1)
        z_norm = np.linalg.norm(z.reshape(-1, z.shape[-1]), axis=0) + 1e-300

    def fit(rows):
        columns, rhs = a[rows].reshape(-1, a.shape[-1]) / norm, y[rows].reshape(-1)
        if instrument is not None:
            instruments = z[rows].reshape(-1, z.shape[-1]) / z_norm
            columns, rhs = instruments.T @ columns, instruments.T @ rhs
        theta, *_ = np.linalg.lstsq(columns, rhs, rcond=None)
        return theta / norm

    theta = fit(np.arange(runs))
    rng = np.random.default_rng(seed)
    boot = np.array([fit(rng.integers(0, runs, runs))[:2] for _ in range(200)])
    residual = y.reshape(-1) - a.reshape(-1, a.shape[-1]) @ theta
    return {
        "damping": theta[:2],
        "interval": np.percentile(boot, [2.5, 97.5], axis=0).T,
        "residual_rms": float(residual.std()),
        "balance_rms": float(y.std()),
        "columns": int(a.shape[-1]),
        "windows": int(y.size),
    }


def _from_state(
    frames, order: int, angles=None, smoothing: tuple[int, int] = (0, 0), instrumented: bool = False
) -> dict:
    """The balance on MuJoCo's states; with `angles`, on those joint angles instead (velocities by the
    frames' filter, or with `instrumented` by `_disjoint` and instrumental variables), while the controls'
    work stays MuJoCo's own."""
    import mujoco
    import numpy as np
    from scipy.signal import savgol_filter

    q, qd = (np.asarray(frames.extras[k], dtype=float) for k in ("qpos", "qvel"))
    true_qd = qd
    scene = mujoco.MjModel.from_xml_string(frames.info["mjcf_xml"])
    torque = np.zeros_like(q)
    for column, name in enumerate(frames.info["actuator_names"]):
        a = mujoco.mj_name2id(scene, mujoco.mjtObj.mjOBJ_ACTUATOR, str(name))
        u = np.asarray(frames.u[..., column], dtype=float)
        if scene.actuator_ctrllimited[a]:  # as MuJoCo applies it (the stock motor clips to [-1, 1])
            u = np.clip(u, *scene.actuator_ctrlrange[a])
        joint = mujoco.mj_id2name(scene, mujoco.mjtObj.mjOBJ_JOINT, scene.actuator_trnid[a, 0])
        torque[..., JOINTS.index(joint)] = scene.actuator_gear[a, 0] * u
    power = (torque * true_qd).sum(-1)
    edge, other, instrument = 0, None, None
    if angles is not None:
        window, degree = smoothing
        q = savgol_filter(angles, window, degree, axis=1)
        qd = savgol_filter(angles, window, degree, deriv=1, delta=frames.dt, axis=1)
        edge = window // 2
        if instrumented:
            qd, other, instrument = _disjoint(angles, window, degree, frames.dt, ends=qd)
    zero = np.zeros(q.shape[:2])
    fit = balance(q, qd, zero, power, frames.dt, order, edge, other=other, instrument=instrument)
    return fit | {"units": "N m s"}


def _estimated_joints(model, spec, frames) -> tuple:
    """The estimator's joint angles of every frame `(runs, samples, 2)` (unwrapped), the model's float64
    dynamics, the joint structure, the keypoints, and the frames with the model's controls in place."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import keyvision
    from keyvision._identify import _place_controls

    frames = _place_controls(
        frames, keyvision.scene_actuators(spec["data"]["scene"]), model.dynamics.num_inputs
    )
    x = np.asarray(
        keyvision.encode_sequences(model, keyvision.ImageSequences.from_frames(frames)).x, dtype=float
    )
    dynamics = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, model.dynamics)
    structure = keyvision.joint_structure(dynamics.constraint, x, JOINTS)
    runs, samples, k = x.shape
    q = np.asarray(jax.vmap(structure.joint_map.inverse)(jnp.asarray(x.reshape(-1, k))))
    return np.unwrap(q.reshape(runs, samples, -1), axis=1), dynamics, structure, x, frames


def _joules(dynamics, structure, x, frames) -> float:
    """Joules per unit of the learnt energy, fixed by the scene's gears (identify's conversion)."""
    from keyvision._identify import actuator_gears, energy_scale, metres_per_unit

    return energy_scale(
        dynamics,
        structure,
        x.reshape(-1, x.shape[-1]),
        actuator_gears(frames.info["mjcf_xml"]),
        metres_per_unit(frames.camera),
    )["joules_per_unit"]


def _polarised(dynamics):
    """`(p, a, b, u) -> (V + a^T M b / 2, u^T B^T (a + b) / 2)`, jitted and batched: the energy with the
    velocity products of two estimates (`E(p, a + b) - E(p, a - b) = 2 a^T M b`) and the work with their
    mean."""
    import jax
    import jax.numpy as jnp

    def polarised(p, a, b, c):
        kinetic = (dynamics.energy(p, a + b) - dynamics.energy(p, a - b)) / 4
        return dynamics.energy(p, jnp.zeros_like(a)) + kinetic, (a + b) / 2 @ (dynamics.input_matrix(p) @ c)

    return jax.jit(jax.vmap(polarised))


def _filters(x, dt: float, windows) -> dict:
    """Savitzky-Golay filters by label: each window of `windows` at degree 3, and the window and degree
    that `cldyn.identify` would choose on the keypoints `x`."""
    import cldyn

    choice = cldyn.Smoothing().choose(x, dt)
    filters = {f"w = {w}": (w, 3) for w in windows}
    filters[f"w = {choice.window}, degree {choice.order} (identify's choice)"] = (choice.window, choice.order)
    return filters


def _from_frames(frames, model, spec, order: int, windows) -> tuple:
    """The balance on the estimator's joints for each Savitzky-Golay window of `windows` (degree 3) and
    for the window and degree that `cldyn.identify` would choose on these keypoints, by least squares and
    by instrumental variables (`_disjoint`); the filters used; and the estimator's error against MuJoCo
    (`_estimator_error`)."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from scipy.signal import savgol_filter

    q, dynamics, structure, x, frames = _estimated_joints(model, spec, frames)
    joints = structure.joint_map
    runs, samples, _ = x.shape
    joules = _joules(dynamics, structure, x, frames)
    u = jnp.asarray(np.asarray(frames.u, dtype=float).reshape(-1, frames.u.shape[-1]))
    energy_and_power = jax.jit(
        jax.vmap(lambda p, v, c: (dynamics.energy(p, v), v @ (dynamics.input_matrix(p) @ c)))
    )
    polarised_energy_and_power = _polarised(dynamics)
    filters = _filters(x, frames.dt, windows)
    tangent = jax.vmap(lambda a, b: jax.jvp(joints.forward, (a,), (b,)))

    def converted(fit):
        return fit | {
            "damping": fit["damping"] * joules,
            "interval": fit["interval"] * joules,
            "units": "N m s",
            "joules_per_model_unit": float(joules),
        }

    controls = np.asarray(frames.u, dtype=float)
    fits = {name: {} for name in FRAME_SOURCES}
    for label, (window, degree) in filters.items():
        smooth = savgol_filter(q, window, degree, axis=1)
        qd = savgol_filter(q, window, degree, deriv=1, delta=frames.dt, axis=1)
        position, velocity = tangent(jnp.asarray(smooth.reshape(-1, 2)), jnp.asarray(qd.reshape(-1, 2)))
        energy, power = (
            np.asarray(v).reshape(runs, samples) for v in energy_and_power(position, velocity, u)
        )
        for name, given in (("frames", None), ("frames, input basis", controls)):
            fit = balance(smooth, qd, energy, power, frames.dt, order, window // 2, controls=given)
            fits[name][label] = converted(fit)
        qa, qb, qc = _disjoint(q, window, degree, frames.dt, ends=qd)
        _, va = tangent(jnp.asarray(smooth.reshape(-1, 2)), jnp.asarray(qa.reshape(-1, 2)))
        _, vb = tangent(jnp.asarray(smooth.reshape(-1, 2)), jnp.asarray(qb.reshape(-1, 2)))
        energy, power = (
            np.asarray(v).reshape(runs, samples) for v in polarised_energy_and_power(position, va, vb, u)
        )
        for name, given in (("frames, instrumented", None), ("frames, instrumented, input basis", controls)):
            fit = balance(
                smooth,
                qa,
                energy,
                power,
                frames.dt,
                order,
                window // 2,
                other=qb,
                instrument=qc,
                controls=given,
            )
            fits[name][label] = converted(fit)
    return (fits, filters, *_estimator_error(q, np.asarray(frames.extras["qpos"], dtype=float)))


def _estimator_error(q, truth) -> tuple:
    """RMS joint-angle error (sign and offset aligned), and the part left after a fixed function of the pose;
    also that function (the warp, added to MuJoCo's angles) and the RMS of the rest per joint."""
    import numpy as np

    signs, errors = [], []
    for j in range(len(JOINTS)):
        best = None
        for sign in (1, -1):
            d = q[..., j] - sign * truth[..., j]
            e = np.angle(np.exp(1j * (d - np.angle(np.exp(1j * d).mean()))))
            if best is None or np.abs(e).mean() < np.abs(best[1]).mean():
                best = (sign, e)
        signs.append(best[0])
        errors.append(best[1])
    error = np.stack(errors, -1)
    rest, warp = _high_order(error, truth, 4)
    rest_rms = rest.reshape(-1, rest.shape[-1]).std(axis=0)
    out = {
        name: {
            "rms_rad": float(np.sqrt((error[..., j] ** 2).mean())),
            "not_a_function_of_pose_rms_rad": float(rest_rms[j]),
        }
        for j, name in enumerate(JOINTS)
    }
    return out, warp * np.array(signs), rest_rms  # the warp in MuJoCo's sense of each angle


def _row(data: str, source: str, fit: dict) -> str:
    cells = [
        f"{fit['damping'][j]:.4f} [{fit['interval'][j][0]:.3f}, {fit['interval'][j][1]:.3f}]"
        for j in range(2)
    ]
    rms = f"{fit['residual_rms']:.3g} / {fit['balance_rms']:.3g}"
    return f"| {data} | {source} | {cells[0]} | {cells[1]} | {rms} |"


def _markdown(result: dict) -> str:
    lines = [
        "# The stock acrobot's damping by energy balance (`benchmarks/vision_energy_balance.py`)",
        "",
        f"{result['runs']} runs of {result['frames']} frames ({result['seconds_per_run']:.2f} s), "
        f"seed {result['seed']}; "
        f"Fourier basis of order {result['order']}. Damping in N m s with its 95% bootstrap interval over "
        "runs; the truth is 0.05 at both joints (stock) and 0 (damping-free). `state`: MuJoCo's joint "
        "states. With a window `w`, velocities come from a Savitzky-Golay filter of `w` samples (degree 3, "
        "or as `cldyn.identify` would choose it on the estimated keypoints): of MuJoCo's angles as they "
        "are (`filtered`), warped by the estimator's pose-dependent error (`+ warp`), with noise of the "
        "size of its remaining error (`+ noise`), and of the estimator's own angles (`frames`, with the "
        "learnt model's energy and input work). `instrumented`: the same fit by instrumental variables, "
        "with three velocity estimates from disjoint samples of each filter's window (offsets 0, 1 and 2 "
        "modulo 3): the columns are made of the first two, the instruments of the third, whose noise is "
        "independent of theirs, so noise in the velocities does not bias the fit as it biases least "
        "squares. `input basis`: the `frames` fits with columns for an error of the learnt input map "
        "through which their work is computed (`int u_k f_i(q) qd_j`, every control, joint and Fourier "
        "term), which the rows on MuJoCo's work do not need.",
    ]
    for name, entry in result["models"].items():
        supersample = next(iter(entry["cases"].values())).get("supersample", 1)
        camera = f", frames of {supersample} x {supersample} samples per pixel" if supersample > 1 else ""
        lines += ["", f"## `{name}` (`{entry['model']}`{camera})", ""]
        lines += [
            "| data | source | shoulder | elbow | residual / balance RMS |",
            "| --- | --- | --- | --- | --- |",
        ]
        for data, row in entry["cases"].items():
            lines.append(_row(data, "state", row["state"]))
            for window, fits in row["windows"].items():
                lines += [_row(data, f"{window}, {source}", fit) for source, fit in fits.items()]
        lines += ["", "The estimator's joint angles against MuJoCo's (radians, RMS):", ""]
        lines += ["| data | joint | error | not a function of the pose |", "| --- | --- | --- | --- |"]
        for data, row in entry["cases"].items():
            for joint, e in row["estimator_error"].items():
                lines.append(
                    f"| {data} | {joint} | {e['rms_rad']:.3f} | {e['not_a_function_of_pose_rms_rad']:.4f} |"
                )
    lines += ["", f"Machine: {result['machine']['platform']}, {result['wall_s']:.0f} s.", ""]
    return "\n".join(lines)


def _jsonable(fit: dict) -> dict:
    return {k: v.tolist() if hasattr(v, "tolist") else v for k, v in fit.items()}


def _cases(model, spec, protocol, args, measured: dict) -> dict:
    """Every row for one model, on frames of the camera it was trained on (`--supersample` for
    another). `measured` keeps the rows that do not depend on the model (MuJoCo's states, as they are
    or filtered), by data set and filter, for the next model: the runs are the same whatever the camera."""
    import dataclasses

    import numpy as np

    import keyvision
    from keyvision._files import trained_supersample

    supersample = args.supersample or trained_supersample(spec)
    protocol = dataclasses.replace(protocol, supersample=supersample)

    def state(data, frames, angles=None, smoothing=(0, 0), instrumented=False):
        key = (data, smoothing, instrumented)
        if key not in measured:
            measured[key] = _from_state(frames, args.order, angles, smoothing, instrumented)
        return measured[key]

    cases = {}
    for data, (source, truth) in SOURCES.items():
        frames = keyvision.render(source, protocol=protocol, seed=args.seed, workers=1)
        from_frames, filters, error, warp, noise = _from_frames(frames, model, spec, args.order, args.windows)
        angles = np.asarray(frames.extras["qpos"], dtype=float)
        jitter = noise * np.random.default_rng(1).standard_normal(angles.shape)
        windows = {}
        for label, smoothing in filters.items():
            windows[label] = {
                "filtered": state(data, frames, angles, smoothing),
                "+ warp": _from_state(frames, args.order, angles + warp, smoothing),
                "+ noise": _from_state(frames, args.order, angles + jitter, smoothing),
                "frames": from_frames["frames"][label],
                "frames, input basis": from_frames["frames, input basis"][label],
                "filtered, instrumented": state(data, frames, angles, smoothing, instrumented=True),
                "+ noise, instrumented": _from_state(
                    frames, args.order, angles + jitter, smoothing, instrumented=True
                ),
                "frames, instrumented": from_frames["frames, instrumented"][label],
                "frames, instrumented, input basis": from_frames["frames, instrumented, input basis"][label],
            }
            print(
                f"{data}, {label}: "
                + "; ".join(f"{name} {from_frames[name][label]['damping']}" for name in FRAME_SOURCES),
                file=sys.stderr,
                flush=True,
            )
        cases[data] = {
            "scene": source,
            "supersample": supersample,
            "true_damping": truth,
            "dt": frames.dt,
            "state": _jsonable(state(data, frames)),
            "windows": {w: {k: _jsonable(f) for k, f in fits.items()} for w, fits in windows.items()},
            "estimator_error": error,
        }
    return cases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=60)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0, help="seed of the rendered runs")
    parser.add_argument(
        "--order", type=int, default=3, help="order of the Fourier basis of the energy's error"
    )
    parser.add_argument(
        "--windows", type=int, nargs="+", default=[9, 15, 25], help="Savitzky-Golay windows (samples, odd)"
    )
    parser.add_argument(
        "--models",
        nargs="+",
        default=[str(path) for path in MODELS],
        help="directories of learnt acrobot models (keyvision.load_model)",
    )
    parser.add_argument(
        "--supersample",
        type=int,
        help="samples per pixel side of the camera (default: each model's training camera, "
        "keyvision.RenderProtocol's supersample)",
    )
    parser.add_argument(
        "--name",
        help="the results' name (default: vision_energy_balance, with _seed<N> for a --seed other than 0)",
    )
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    import keyvision

    started = time.perf_counter()
    protocol = keyvision.RenderProtocol(
        runs=args.runs, validation_runs=min(10, args.runs - 1), frames=args.frames
    )
    models, measured = {}, {}
    for directory in args.models:
        model, spec = keyvision.load_model(directory)
        path = pathlib.Path(directory).resolve()
        models[path.name] = {
            "model": repo_path(path),
            "cases": _cases(model, spec, protocol, args, measured),
        }
    dt = next(iter(next(iter(models.values()))["cases"].values()))["dt"]
    result = {
        "runs": args.runs,
        "frames": args.frames,
        "seed": args.seed,
        "seconds_per_run": (args.frames - 1) * dt,
        "order": args.order,
        "windows": args.windows,
        "models": models,
        "wall_s": time.perf_counter() - started,
        "machine": machine(),
    }
    name = args.name or "vision_energy_balance" + (f"_seed{args.seed}" if args.seed else "")
    write(name, result, _markdown(result))


if __name__ == "__main__":
    main()
