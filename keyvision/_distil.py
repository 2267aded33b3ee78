"""Shift distillation: an estimator taught its own reading averaged over the U-Net's pooling phases.

A U-Net with two 2x2 poolings is equivariant to shifts of 4 pixels, not of one: a frame shifted by
a pixel is read through another of its 16 pooling phases, and each phase reads the keypoints a
little differently. Averaged over the 16 (each reading moved back by its shift) the reading is
smoother in the pose, which is what a controller's gain at a target needs; but it costs 16 passes
a frame. `distil_shifts` fine-tunes the estimator so that one pass gives that average: the teacher
is the estimator itself, read through the 16 phases once per training frame, and the student reads
frames shifted at random against the teacher's reading moved by the same shift. No labels are
involved: the estimator stays the one learnt from images without supervision.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, PRNGKeyArray

import cldyn
from cldyn._misc import check_positive
from cldyn._steps import optax_promotion

from ._control import _as_images as as_images
from ._estimator import AbstractKeypointEstimator
from ._model import KeyCLD
from ._train import _clipped_adam

__all__ = ["shift_average", "distil_shifts"]


def _shift(images: Array, dy: Array, dx: Array, pad: int) -> Array:
    # content moved down by dy and right by dx pixels, the border repeated into the gap
    size = images.shape[-3:]
    padded = jnp.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    return jax.vmap(lambda image, a, b: jax.lax.dynamic_slice(image, (pad - a, pad - b, 0), size))(
        padded, dy, dx
    )


def _moves(dy: Array, dx: Array, image_size: int, dtype) -> Array:
    # a shift of the content in pixels as a move of the keypoints in frame units (x right, y up)
    return (jnp.stack([2 * dx, -2 * dy], -1)[..., None, :] / image_size).astype(dtype)


def shift_average(estimator: AbstractKeypointEstimator, images: Array, phases: int = 4) -> Array:
    """The estimator's reading of each image averaged over shifts of `0 .. phases - 1` pixels
    each way (`phases**2` readings, each moved back by its shift; the border is repeated into the
    gap), the teacher of `keyvision.distil_shifts`.

    **Arguments:**

    - `estimator`: a `keyvision.AbstractKeypointEstimator`.
    - `images`: `(B, H, W, C)` floating images in `[0, 1]`.
    - `phases`: shifts per axis; 4 covers the 16 pooling phases of the U-Net's two 2x2 poolings.

    **Returns:** `(B, K, 2)` keypoints.
    """
    check_positive("shift_average: phases", phases, integer=True)
    if images.ndim != 4:
        raise ValueError(f"shift_average: images must be (B, H, W, C), got shape {images.shape}")
    count, size = images.shape[0], images.shape[1]
    padded = jnp.pad(images, ((0, 0), (phases, phases), (phases, phases), (0, 0)), mode="edge")
    shifts = [(a, b) for a in range(phases) for b in range(phases)]
    # one batch of every shifted copy through the estimator, unrolled: XLA's CPU backend runs
    # convolutions inside a compiled loop several times slower
    crops = [padded[:, phases - a : phases - a + size, phases - b : phases - b + size] for a, b in shifts]
    readings = jax.vmap(estimator)(jnp.concatenate(crops)).reshape(len(shifts), count, -1, 2)
    dy, dx = (jnp.asarray([shift[axis] for shift in shifts]) for axis in (0, 1))
    return jnp.mean(readings - _moves(dy, dx, size, images.dtype)[:, None], axis=0)


def distil_shifts(
    model: KeyCLD,
    frames,
    *,
    key: PRNGKeyArray,
    steps: int = 2000,
    batch_size: int = 32,
    learning_rate: float = 3e-4,
    phases: int = 4,
    progress_meter: cldyn.AbstractProgressMeter = cldyn.NoProgressMeter(),
) -> tuple[KeyCLD, dict]:
    """Fine-tune a model's estimator to read in one pass what it reads averaged over the U-Net's
    pooling phases (`keyvision.shift_average`): a controller's reading as smooth in the pose as the
    average's at the cost of one pass (see the module's description; unsupervised).

    **Arguments:**

    - `model`: a trained `keyvision.KeyCLD`; only its estimator changes.
    - `frames`: training frames `(..., H, W, C)`, uint8 `0..255` or float in `[0, 1]` (the model's
      training runs, or a sample of them).
    - `key`: a `jax.random` key for the batches and the shifts.
    - `steps`, `batch_size`, `learning_rate`: Adam (gradients clipped at 5) with a warm-up and a cosine
      decay to a tenth, as the stages of `keyvision.train`.
    - `phases`: shifts per axis of the teacher, and the range of the student's random shifts
      (`-(phases - 1) .. phases - 1` pixels each way).
    - `progress_meter`: e.g. `cldyn.TextProgressMeter()`; the teacher's reading counts as its first
      unit.

    **Returns:** `(model, report)`: the model with the fine-tuned estimator, and the root mean square
    distance (frame units) of the estimator's one-pass reading from the teacher's over the frames,
    before and after. A loss that is not finite raises `FloatingPointError` naming the step (the
    model passed in is left as it was).
    """
    if not isinstance(model, KeyCLD):
        raise TypeError(f"distil_shifts: model must be a keyvision.KeyCLD, got {type(model).__name__}")
    for name, value in (("steps", steps), ("batch_size", batch_size), ("phases", phases)):
        check_positive(f"distil_shifts: {name}", value, integer=True)
    check_positive("distil_shifts: learning_rate", learning_rate)
    frames = np.asarray(frames)
    size, channels = model.estimator.image_size, getattr(model.estimator, "channels", 3)
    if frames.ndim < 4 or frames.shape[-3:] != (size, size, channels):
        raise ValueError(
            f"distil_shifts: frames must be (..., {size}, {size}, {channels}) for this model, "
            f"got shape {frames.shape}"
        )
    frames = frames.reshape(-1, size, size, channels)
    if not np.all(np.isfinite(frames)):
        raise ValueError("distil_shifts: frames contain NaN or infinite values")
    as_images(frames[:1])  # refuses a dtype other than uint8 and floating before any work
    chunk = 16

    teach = eqx.filter_jit(lambda e, b: shift_average(e, as_images(b), phases))
    read = eqx.filter_jit(lambda e, b: jax.vmap(e)(as_images(b)))

    def over(fn, estimator):
        pieces = [fn(estimator, frames[i : i + chunk]) for i in range(0, len(frames), chunk)]
        return np.concatenate([np.asarray(piece) for piece in pieces])

    meter = progress_meter.start(steps + 1, desc="distil shifts", unit="step")
    try:
        targets = over(teach, model.estimator)
        before = float(np.sqrt(np.mean((over(read, model.estimator) - targets) ** 2)))
        meter = progress_meter.update(meter, 1, {"rms": before})
        warmup = min(100, steps // 10)
        optimizer = _clipped_adam(learning_rate, warmup, max(steps, warmup + 1), 0.1 * learning_rate)
        params, static = eqx.partition(model.estimator, eqx.is_inexact_array)
        state = optimizer.init(params)
        span = phases - 1

        @eqx.filter_jit
        def step(params, state, batch, target, key):
            ky, kx = jax.random.split(key)
            dy = jax.random.randint(ky, (batch.shape[0],), -span, span + 1)
            dx = jax.random.randint(kx, (batch.shape[0],), -span, span + 1)
            images = _shift(as_images(batch), dy, dx, max(span, 1))
            target = target + _moves(dy, dx, size, target.dtype)

            def loss(p):
                return jnp.mean((jax.vmap(eqx.combine(p, static))(images) - target) ** 2)

            value, grads = jax.value_and_grad(loss)(params)
            with optax_promotion():
                updates, state = optimizer.update(grads, state, params)
            return optax.apply_updates(params, updates), state, value, jnp.isfinite(value)

        keys = jax.random.split(key, steps + 1)
        rng = np.random.default_rng(np.asarray(jax.random.key_data(keys[0])).ravel())
        for i in range(steps):
            index = rng.integers(0, len(frames), batch_size)
            params, state, value, finite = step(params, state, frames[index], targets[index], keys[i + 1])
            if not bool(finite):
                raise FloatingPointError(f"distil_shifts: the loss is not finite at step {i}")
            if (i + 1) % 50 == 0 or i + 1 == steps:
                meter = progress_meter.update(meter, i + 2, {"loss": float(value)})
        estimator = eqx.combine(params, static)
        after = float(np.sqrt(np.mean((over(read, estimator) - targets) ** 2)))
    finally:
        progress_meter.close(meter)
    model = eqx.tree_at(lambda m: m.estimator, model, estimator)
    return model, {"rms_before": before, "rms_after": after, "frames": len(frames), "phases": phases}
