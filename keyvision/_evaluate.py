"""Evaluation of KeyCLD models on frames: prediction, the valid prediction time (eq. 16), and
diagnostics of learned keypoints against the ground truth rendered with the frames."""

from collections.abc import Sequence

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

import cldyn
from cldyn._evaluate import failed_samples

from ._data import Frames, ImageSequences, as_images
from ._keypoints import frame_to_pixel
from ._model import KeyCLD, parameter_dtype

_ENCODE_FRAMES = 256  # frames per call when encoding a dataset: bounds the memory of the activations


def pose_features(frames: Frames) -> Float[np.ndarray, "R T P"]:
    """The true pose as features that an affine map of good keypoints can reproduce: `sin` and `cos`
    of every hinge angle, and the position of every slide.

    **Arguments:**

    - `frames`: rendered `keyvision.Frames` (with `extras["qpos"]` and the joint types in `info`).

    **Returns:** `(R, T, P)` features, `P = 2 * hinges + slides`.

    !!! example

        ```python
        truth = keyvision.pose_features(frames)     # pendulum: (R, T, 2) = sin, cos of the angle
        ```
    """
    qpos = np.asarray(frames.extras["qpos"])
    columns = []
    for kind, index in zip(frames.info["joint_types"], frames.info["joint_qpos_index"]):
        if kind == "hinge":
            columns += [np.sin(qpos[..., index]), np.cos(qpos[..., index])]
        elif kind == "slide":
            columns.append(qpos[..., index])
        else:
            raise ValueError(f"pose_features: a {kind} joint has no planar pose feature")
    return np.stack(columns, axis=-1)


def keypoint_tracking(
    estimated: Float[np.ndarray, "N ..."],
    truth_pose: Float[np.ndarray, "N ... P"],
    *,
    fit_fraction: float = 0.5,
) -> float:
    """How well learned keypoints track the true pose: the held-out `R^2` of an affine map from the
    keypoints to the pose features.

    An affine map `truth ~ A @ keypoints + b` is fitted by least squares on the first
    `fit_fraction` of the leading axis (e.g. runs) and scored on the rest:

    $$R^2 = 1 - \\frac{\\sum \\lVert y - \\hat y \\rVert^2}{\\sum \\lVert y - \\bar y \\rVert^2}$$

    pooled over all features, with `\\bar y` the mean over the held-out rows. 1 means the keypoints
    determine the pose (up to an affine map: units, orientation and offset of the image frame are
    free); 0 means they explain no more than the mean pose. Keypoints that slide along a body, or
    settle on the background, score low even when the reconstruction looks right.

    **Arguments:**

    - `estimated`: keypoints, `(N, ..., K, 2)` or `(N, ..., 2K)`, e.g. `(R, T, K, 2)`.
    - `truth_pose`: the matching pose features `(N, ..., P)`, e.g. `keyvision.pose_features(frames)`.
    - `fit_fraction`: the fraction of the leading axis used to fit the map (the rest scores it).

    **Returns:** the held-out `R^2` (at most 1; negative if the map does worse than the mean).

    !!! example

        ```python
        keypoints = jax.vmap(jax.vmap(estimator))(frames.images())      # (R, T, K, 2)
        keyvision.keypoint_tracking(keypoints, keyvision.pose_features(frames))
        ```
    """
    estimated = np.asarray(estimated, dtype=float)
    truth = np.asarray(truth_pose, dtype=float)
    leading = truth.shape[:-1]
    if estimated.shape[: len(leading)] != leading:
        raise ValueError(
            f"keypoint_tracking: estimated {estimated.shape} and truth_pose {truth.shape} disagree in "
            f"their leading axes {leading}"
        )
    if not 0 < fit_fraction < 1:
        raise ValueError(f"keypoint_tracking: fit_fraction must lie in (0, 1), got {fit_fraction}")
    cut = int(round(fit_fraction * leading[0]))
    if not 0 < cut < leading[0]:
        raise ValueError(f"keypoint_tracking: {leading[0]} rows cannot be split at fraction {fit_fraction}")
    inputs = estimated.reshape(*leading, -1)
    design = np.concatenate([inputs, np.ones((*leading, 1))], axis=-1)
    fit_x, test_x = design[:cut].reshape(-1, design.shape[-1]), design[cut:].reshape(-1, design.shape[-1])
    fit_y, test_y = truth[:cut].reshape(-1, truth.shape[-1]), truth[cut:].reshape(-1, truth.shape[-1])
    coefficients, *_ = np.linalg.lstsq(fit_x, fit_y, rcond=None)
    residual = np.sum((test_x @ coefficients - test_y) ** 2)
    spread = np.sum((test_y - test_y.mean(axis=0)) ** 2)
    return float(1 - residual / spread)


def _frame_mse(predicted, truth) -> Array:
    return jnp.mean((predicted - truth) ** 2, axis=(-3, -2, -1))


def prediction_threshold(images: Float[ArrayLike, "*runs T H W C"]) -> float:
    """The error threshold of the valid prediction time: the mean squared error of a static
    prediction by the dataset's mean image (paper section 4).

    $\\varepsilon = \\operatorname{mean}_{r, i} \\operatorname{MSE}(z_{r,i}, \\bar z)$ with $\\bar z$ the
    mean of all frames of all runs: a model that predicts no motion scores this.

    **Arguments:**

    - `images`: every frame of the (validation) dataset, values in `[0, 1]`, e.g. `(R, T, H, W, 3)`.

    **Returns:** `epsilon`, a float.

    !!! example

        ```python
        epsilon = keyvision.prediction_threshold(validation.images())
        ```
    """
    images = jnp.asarray(images)
    if images.ndim < 4:
        raise ValueError(f"prediction_threshold: images must be (..., T, H, W, C), got {images.shape}")
    flat = images.reshape(-1, *images.shape[-3:])
    return float(jnp.mean(_frame_mse(flat, jnp.mean(flat, axis=0, keepdims=True))))


def valid_prediction_time(
    predicted: Float[ArrayLike, "*runs T H W C"],
    truth: Float[ArrayLike, "*runs T H W C"],
    *,
    threshold: float | None = None,
) -> Float[Array, "*runs"]:
    """The valid prediction time (VPT, eq. 16) of predicted frames: the index of the first frame
    whose mean squared error exceeds the threshold, as a fraction of the `T` frames.

    $\\mathrm{VPT} = \\frac{1}{T} \\min \\{ i : \\operatorname{MSE}(z'_i, z_i) > \\varepsilon \\}$, and 1
    when no frame exceeds it (Table 1 of the paper reports this fraction). A frame whose error is not
    a number (predicted by a rollout that failed, see `predict`) exceeds it. This is the image-space
    metric of the paper; `cldyn.valid_prediction_time` is its state-space counterpart (a distance
    between keypoints, not a pixel error).

    **Arguments:**

    - `predicted`, `truth`: frames with values in `[0, 1]`, shape `(..., T, H, W, C)`.
    - `threshold`: `epsilon`; by default `prediction_threshold(truth)`, right when `truth` is the
      whole validation set.

    **Returns:** the VPT of every run, shape `(...)`, between 0 and 1.

    !!! example

        ```python
        predicted = jax.vmap(keyvision.predict, in_axes=(None, 0, 0, None))(model, images, u, dt)
        vpt = keyvision.valid_prediction_time(predicted, images)   # (R,)
        ```
    """
    predicted, truth = jnp.asarray(predicted), jnp.asarray(truth)
    if predicted.shape != truth.shape or predicted.ndim < 4:
        raise ValueError(
            "valid_prediction_time: predicted and truth must have the same shape (..., T, H, W, C), "
            f"got {predicted.shape} and {truth.shape}"
        )
    epsilon = prediction_threshold(truth) if threshold is None else float(threshold)
    if not epsilon > 0:
        raise ValueError(f"valid_prediction_time: the threshold must be positive, got {epsilon}")
    exceeded = ~(_frame_mse(predicted, truth) <= epsilon)  # NaN frames (a failed prediction) exceed it
    samples = exceeded.shape[-1]
    first = jnp.where(jnp.any(exceeded, axis=-1), jnp.argmax(exceeded, axis=-1), samples)
    return first / samples


def predict_keypoints(
    model: KeyCLD,
    images: Float[ArrayLike, "T H W C"],
    controls: Float[ArrayLike, "T l"],
    dt: float,
    *,
    solver: dfx.AbstractSolver = cldyn.RK4(),
    stabilisation: cldyn.AbstractStabilisation | None = cldyn.Projection(),
    throw: bool = True,
) -> Float[Array, "T k"]:
    """The keypoints that `predict` renders: frame 0 encoded, frames `1 .. T-1` integrated.

    Takes the arguments of `predict` (see there); returns `(T, k)` keypoints in the image frame,
    aligned with `images` (with `throw=False`, NaN from the failure of a rollout that fails on).
    `draw_keypoints` marks them on frames.
    """
    images, controls = jnp.asarray(images), jnp.asarray(controls)
    if images.ndim != 4 or images.shape[0] < 3:
        raise ValueError(f"predict: images must be (T, H, W, C) with T >= 3 frames, got {images.shape}")
    if controls.ndim != 2 or controls.shape[0] != images.shape[0]:
        raise ValueError(f"predict: controls must be ({images.shape[0]}, l), got {controls.shape}")
    x = model.encode(images[:3])
    run = cldyn.rollout(
        model.dynamics, x[1], (x[2] - x[0]) / (2 * dt), controls[1:].astype(x.dtype), dt,
        solver=solver, stabilisation=stabilisation, project=True, throw=throw,
    )
    if throw:
        return jnp.concatenate([x[:1], run.x], axis=0)
    failed = failed_samples(run)[:, None]  # NaN from the failure on
    return jnp.concatenate([x[:1], jnp.where(failed, jnp.nan, run.x)], axis=0)


def predict(
    model: KeyCLD,
    images: Float[ArrayLike, "T H W C"],
    controls: Float[ArrayLike, "T l"],
    dt: float,
    *,
    solver: dfx.AbstractSolver = cldyn.RK4(),
    stabilisation: cldyn.AbstractStabilisation | None = cldyn.Projection(),
    throw: bool = True,
) -> Float[Array, "T H W 3"]:
    """Predict the frames of a run from its first three: encode, integrate the dynamics, render.

    The first three frames are encoded; the state at frame 1 is the keypoints and their central
    difference $(x_2 - x_0) / 2h$ (eq. 11), projected onto the constraint tangent space, and
    `cldyn.rollout` integrates it with the run's controls held between frames (`solver`, with
    `stabilisation` keeping the constraints at the values measured at frame 1, not at fixed
    lengths). Frame 0 of the result is the reconstruction of frame 0; frames `1 .. T-1` are
    rendered from the rollout. One run in, one out: `jax.vmap` it over runs.

    **Arguments:**

    - `model`: a `keyvision.KeyCLD`.
    - `images`: the run's `T >= 3` frames, values in `[0, 1]` (only the first three are used).
    - `controls`: `(T, l)` the controls held from each frame to the next.
    - `dt`: the time between frames.
    - `solver`: a diffrax solver; `cldyn.RK4()` (one step per frame) by default.
    - `stabilisation`: `cldyn.Projection()` by default.
    - `throw`: raise when the rollout fails (a projection that does not converge: a model that
      breaks its own constraints); with `False` the frames from the failure on are NaN, which
      `valid_prediction_time` counts as exceeding the threshold (how `keyvision evaluate` scores).

    **Returns:** `(T, H, W, 3)` predicted frames, aligned with `images`.

    !!! example

        ```python
        images = validation.images()                       # (R, T, 64, 64, 3)
        predicted = jax.vmap(lambda z, u: keyvision.predict(model, z, u, validation.dt))(
            images, validation.u)
        vpt = keyvision.valid_prediction_time(predicted, images)
        ```
    """
    keypoints = predict_keypoints(
        model, images, controls, dt, solver=solver, stabilisation=stabilisation, throw=throw
    )
    return _decode_finite(model, keypoints)


def _decode_finite(model, keypoints):
    # frames drawn from keypoints that are not finite are NaN: a Gaussian map at an infinite
    # keypoint is zero, and the renderer would draw the scene without the body
    finite = jnp.all(jnp.isfinite(keypoints), axis=-1)[..., None, None, None]
    return jnp.where(finite, model.decode(jnp.where(finite[..., 0, 0], keypoints, 0.0)), jnp.nan)


def draw_keypoints(
    frames: Float[ArrayLike, "*batch H W 3"],
    keypoints: Float[ArrayLike, "*batch k"],
    *,
    radius: int = 1,
    colors: Sequence[tuple[float, float, float]] | None = None,
) -> np.ndarray:
    """Frames with their keypoints marked: a filled square of `2 radius + 1` pixels on each.

    For looking at what the estimator tracks. A keypoint at image-frame point `(x, y)` (DESIGN.md:
    `[-1, 1]`, y up) marks the pixel `keyvision.frame_to_pixel` rounds it to and its neighbours
    within `radius`; keypoints outside the image or not finite are left out, and NaN pixels (the
    frames of a failed prediction, see `predict`) are drawn black.

    **Arguments:**

    - `frames`: images with values in `[0, 1]` (float) or `0..255` (uint8), `(..., H, W, 3)`.
    - `keypoints`: `(..., 2K)` keypoints `(x0, y0, x1, y1, ...)` in the image frame, one set per frame.
    - `radius`: half the side of each mark, in pixels.
    - `colors`: an RGB colour in `[0, 1]` per keypoint; a fixed palette by default.

    **Returns:** uint8 frames `(..., H, W, 3)` with the marks.

    !!! example

        ```python
        marked = keyvision.draw_keypoints(images[0], model.encode(images[0]))   # (T, H, W, 3) uint8
        ```
    """
    frames, keypoints = np.asarray(frames), np.asarray(keypoints, dtype=float)
    if frames.ndim < 3 or frames.shape[-1] != 3 or keypoints.shape[-1] % 2:
        raise ValueError(
            f"draw_keypoints: frames must be (..., H, W, 3) and keypoints (..., 2K), got {frames.shape} "
            f"and {keypoints.shape}"
        )
    if frames.shape[:-3] != keypoints.shape[:-1]:
        raise ValueError(
            f"draw_keypoints: {frames.shape[:-3]} frames but keypoints for {keypoints.shape[:-1]}"
        )
    if radius < 0:
        raise ValueError(f"draw_keypoints: radius must be >= 0, got {radius}")
    if frames.dtype == np.uint8:
        out = frames.copy()
    else:
        out = np.round(255 * np.clip(np.nan_to_num(frames, nan=0.0), 0, 1)).astype(np.uint8)
    height, width = out.shape[-3:-1]
    points = keypoints.reshape(keypoints.shape[:-1] + (-1, 2))
    palette = np.asarray(_PALETTE if colors is None else colors, dtype=float)
    if colors is not None and palette.shape != (points.shape[-2], 3):
        raise ValueError(
            f"draw_keypoints: colors must hold one RGB colour per keypoint, ({points.shape[-2]}, 3), got "
            f"{palette.shape}"
        )
    pixels = np.asarray(frame_to_pixel(points, height, width))
    finite = np.all(np.isfinite(pixels), axis=-1, keepdims=True)
    pixels = np.where(finite, np.round(np.where(finite, pixels, 0)), -1).astype(int)  # (..., K, 2)
    flat_out, flat_pixels = out.reshape(-1, height, width, 3), pixels.reshape(-1, points.shape[-2], 2)
    for frame, marks in zip(flat_out, flat_pixels):
        for index, (row, col) in enumerate(marks):
            if not (0 <= row < height and 0 <= col < width):
                continue
            colour = np.round(255 * palette[index % len(palette)]).astype(np.uint8)
            frame[max(row - radius, 0) : row + radius + 1, max(col - radius, 0) : col + radius + 1] = colour
    return out


_PALETTE = ((1.0, 0.0, 0.0), (0.0, 0.8, 1.0), (1.0, 1.0, 0.0), (0.0, 1.0, 0.0), (1.0, 0.0, 1.0))


@eqx.filter_jit
def _predict_batch(model, z, u, dt: float):
    # the model an argument, not a constant of the compiled function: models of one structure (the
    # stages of a training, a model before and after a refit) share one compilation
    def one(z, u):  # a rollout that fails is scored, not raised: its frames from the failure on are NaN
        keypoints = predict_keypoints(model, z, u, dt, throw=False)
        return keypoints, _decode_finite(model, keypoints)

    return jax.vmap(one)(z, u)


@eqx.filter_jit
def encode_batch(model: KeyCLD, frames: Array) -> Array:
    """The keypoints `(..., 2K)` of frames `(..., H, W, C)` of any dtype `as_images` takes (compiled
    once per model structure and shape)."""
    return model.encode(as_images(frames, parameter_dtype(model.estimator)))


def encode_sequences(model: KeyCLD, data: ImageSequences) -> cldyn.Sequences:
    """The keypoints of every frame of `data` as a `cldyn.Sequences` (with the controls and `dt`).

    Frames are encoded a few hundred at a time, so a whole dataset fits in memory.

    **Arguments:**

    - `model`: a `keyvision.KeyCLD`.
    - `data`: `keyvision.ImageSequences`.

    **Returns:** `cldyn.Sequences` with `x` `(runs, T, 2K)` in the image frame.

    !!! example

        ```python
        keypoints = keyvision.encode_sequences(model, data)
        result = cldyn.fit(model.dynamics, keypoints, loss=cldyn.Collocation(), steps=2000, key=key)
        ```
    """
    runs, samples = data.num_runs, data.num_samples
    chunk = max(1, min(runs, _ENCODE_FRAMES // samples))
    padded = -runs % chunk
    frames = np.asarray(data.frames)
    if padded:
        frames = np.concatenate([frames, np.repeat(frames[-1:], padded, axis=0)], axis=0)
    parts = [encode_batch(model, frames[i : i + chunk]) for i in range(0, runs + padded, chunk)]
    x = jnp.concatenate(parts, axis=0)[:runs]
    return cldyn.Sequences(x, jnp.asarray(data.u).astype(x.dtype), data.dt)


def json_number(value) -> float | None:
    """A number for JSON: a float, or None (null) where it is not finite (JSON has no NaN)."""
    return float(value) if np.isfinite(value) else None


@eqx.filter_jit
def decode_batch(model, keypoints):
    """The frames drawn from keypoints `(..., 2K)` (compiled once per model structure; the
    counterpart of `encode_batch`)."""
    return model.decode(keypoints)


def predict_runs(model, images, controls, dt: float, batch: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Every run's predicted keypoints and frames, `batch` runs per compiled call (the last call
    padded to the same shape)."""
    predict = lambda z, u: _predict_batch(model, z, u, float(dt))
    runs = images.shape[0]
    batch = min(batch, runs)
    parts = []
    for start in range(0, runs, batch):
        z, u = images[start : start + batch], controls[start : start + batch]
        missing = batch - z.shape[0]
        if missing:
            z, u = (np.concatenate([a, np.repeat(a[-1:], missing, axis=0)]) for a in (z, u))
        parts.append([np.asarray(a)[: batch - missing] for a in predict(z, u)])
    return tuple(np.concatenate(arrays) for arrays in zip(*parts))
