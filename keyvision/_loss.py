"""The losses of learning from images (paper eq. 10-13): cldyn losses over batches of `ImageSequences`.

Each is a `cldyn.AbstractLoss`, so they add up and scale with cldyn's own losses'
`+` and `*` (`Reconstruction() + 0.1 * KeypointDynamics(cldyn.Collocation())`) and train through
`cldyn.fit`. The dynamics term wraps any cldyn loss rather than copying one: the frames of the batch
are encoded and the wrapped loss sees a `cldyn.Sequences` of the keypoints.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from cldyn import AbstractLoss, Anchor, Distance, Sequences, Stack

from ._augment import transform_images
from ._data import ImageSequences
from ._estimator import KeypointEstimator
from ._keypoints import gaussian_maps, spatial_softmax
from ._model import KeyCLD, parameter_dtype

# `log(1 - h)` is clamped where the normalised heatmap reaches 1 (at its own maximum): the binary
# cross-entropy stays finite, and so does its gradient (no `inf * 0`).
_LOG_FLOOR = 1e-6


def _images(model: KeyCLD, batch: ImageSequences) -> Array:
    if not isinstance(batch, ImageSequences):
        raise TypeError(f"image losses take a keyvision.ImageSequences batch, got {type(batch).__name__}")
    return batch.images(parameter_dtype(model.estimator))


class Reconstruction(AbstractLoss):
    """The reconstruction loss (eq. 10): every frame is encoded to keypoints and rendered back,
    $L_r = \\operatorname{mean} \\lVert z'_i - z_i \\rVert^2$ over frames, pixels and colour channels
    (eq. 10 sums over the frames; the mean keeps the weights of a sum of losses independent of the
    batch and the image size).

    !!! example

        ```python
        loss = keyvision.Reconstruction() + 0.1 * keyvision.KeypointDynamics(cldyn.Collocation())
        value = loss(model, batch)   # model: keyvision.KeyCLD, batch: keyvision.ImageSequences
        ```
    """

    def __call__(self, model: KeyCLD, batch: ImageSequences) -> Array:
        images = _images(model, batch)
        reconstructed = model.decode(model.encode(images, batch.transforms))
        return jnp.mean((reconstructed - images) ** 2)


class KeypointDynamics(AbstractLoss):
    """A cldyn dynamics loss on the encoded keypoints: the frames of each run are encoded
    (`KeyCLD.encode`) and `loss` is applied to `model.dynamics` with the keypoints, the controls and
    the frame interval as a `cldyn.Sequences`. Gradients reach the estimator through the keypoints.

    With `cldyn.Collocation()` this is the paper's $L_d$ (eq. 11-13); `cldyn.Rollout(steps=4)` is the
    multi-step explicit-Euler loss of the authors' later code.

    **Arguments:**

    - `loss`: any cldyn loss over `Sequences`, e.g. `cldyn.Collocation()`, `cldyn.Rollout()`, or a
      weighted sum of them.

    !!! example

        ```python
        loss = keyvision.Reconstruction() + 0.1 * keyvision.KeypointDynamics(cldyn.Collocation())
        ```
    """

    loss: AbstractLoss

    def __check_init__(self):
        if not isinstance(self.loss, AbstractLoss):
            raise TypeError(f"KeypointDynamics wraps a cldyn loss, got {type(self.loss).__name__}")

    def __call__(self, model: KeyCLD, batch: ImageSequences) -> Array:
        x = model.encode(_images(model, batch), batch.transforms)
        keypoints = Sequences(x, jnp.asarray(batch.u).astype(x.dtype), batch.dt)
        return self.loss(model.dynamics, keypoints)


class ConstraintDrift(AbstractLoss):
    """The drift of the constraint values of the encoded keypoints along each window of frames, or
    over the whole batch (`pooled=True`).

    Holonomic constraints hold at a constant value along a run (a pole keeps its length, a cart its
    height), but reconstruction cannot tell keypoints on the bodies from any smooth remapping of
    them: the renderer learns the inverse, and an estimator may well place a keypoint whose distance
    to another swells and shrinks by a few per cent as the mechanism turns. Dynamics fitted to such
    keypoints cannot be those of the rigid mechanism. With $\\Phi$ the constraints of
    `model.dynamics` and $x_{r,i}$ the keypoints of frame $i$ of window $r$,

    $$L_\\Phi = \\operatorname{mean}_{r, c}\\ \\operatorname{var}_i\\ \\Phi_c(x_{r,i}),$$

    a squared length in the image frame (cldyn's constraints are distances and coordinates), zero
    exactly when every constraint value is constant along every window, whatever that value. Only
    the Jacobian of the constraints enters the dynamics (eq. 6), and this term asks no more: the
    lengths stay free. Needs windows of at least two frames and dynamics with constraints.

    With `pooled=True` the variance is taken over every frame of every window of the batch,
    $\\operatorname{mean}_c \\operatorname{var}_{r, i} \\Phi_c(x_{r,i})$: zero exactly when each
    constraint value is one constant in all of them. A mechanism's lengths are the same in every
    run, and the windows of a batch come from different runs in different poses; along one short
    window the pose barely changes, so a keypoint that slides along its link with the pose keeps each
    window's values nearly constant. An acrobot estimator did just that (its first keypoint at the
    elbow when hanging, halfway up the first link at upright: that link's length spread 2.5 pixels
    over the validation frames, 0.7 along a run), and the per-window term left it there; the pooled
    one brought the spread to 0.35 pixels. Like the per-window term it is a squared length, smaller
    for shorter links: from an autoencoder whose keypoints were already close it drew two of them
    together (`docs/images.md`, "Control from frames"). Any batch of at least two frames will do.

    With `relative=True` the variance of each distance constraint (`cldyn.Anchor`,
    `cldyn.Distance`) is divided by the square of its mean over the same frames,
    $\\operatorname{var} \\Phi_c / (\\operatorname{mean} \\Phi_c)^2$: the squared relative spread of
    a length, the same for a link drawn at any size, so the term cannot be lowered by drawing
    keypoints together. Other constraints (a coordinate, whose mean may be zero) keep their plain
    variance. Neither form can tell a keypoint that holds still from one on a body: a keypoint
    that hardly moves keeps its distance from a pivot as well as one on the bob, and scores as well
    (`keyvision.constraint_score`, which judges autoencoders after the fact, sets each constraint's
    variance against the keypoints' own motion for that reason). Reconstruction is what keeps such a
    keypoint from standing still here.

    **Fields:**

    - `pooled`: the variance over the whole batch (`True`) or along each window (`False`).
    - `relative`: each distance's variance over its mean square (`True`) or as it is (`False`).

    !!! example

        ```python
        loss = keyvision.Reconstruction() + 10.0 * keyvision.ConstraintDrift(pooled=True)
        ```
    """

    pooled: bool = eqx.field(default=False, static=True)
    relative: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        for name in ("pooled", "relative"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"ConstraintDrift: {name} must be True or False, got {getattr(self, name)!r}")

    def __call__(self, model: KeyCLD, batch: ImageSequences) -> Array:
        constraint = getattr(model.dynamics, "constraint", None)
        if constraint is None:
            raise TypeError(
                "ConstraintDrift needs dynamics with constraints (a cldyn.ConstrainedLagrangian with a "
                f"constraint), got {type(model.dynamics).__name__} without one"
            )
        x = model.encode(_images(model, batch), batch.transforms)
        if x.ndim != 3 or x.shape[1] * (x.shape[0] if self.pooled else 1) < 2:
            needs = "a batch of at least 2 frames" if self.pooled else "windows of at least 2 frames"
            raise ValueError(f"ConstraintDrift: needs {needs}, got keypoints {x.shape}")
        values = jax.vmap(jax.vmap(constraint))(x)  # (windows, frames, constraints)
        if self.pooled:
            values = values.reshape(1, -1, values.shape[-1])  # one window of every frame
        return constraint_drift(constraint, values, relative=self.relative)


def constraint_drift(constraint, values: Array, *, relative: bool) -> Array:
    """`ConstraintDrift`'s value from the constraint values `(windows, frames, constraints)`: each
    constraint's variance along the frames of each window (over its mean square for a distance
    with `relative`), averaged over windows and constraints."""
    variance = jnp.var(values, axis=1)
    if relative:
        lengths = jnp.asarray(_distance_rows(constraint))
        square = jnp.maximum(jnp.mean(values, axis=1) ** 2, jnp.finfo(values.dtype).tiny)
        variance = jnp.where(lengths, variance / square, variance)
    return jnp.mean(variance)


def _distance_rows(constraint) -> tuple[bool, ...]:
    """For each row of `constraint`'s values: whether it is a distance (`Anchor`, `Distance`)."""
    if isinstance(constraint, Stack):
        return tuple(row for part in constraint.constraints for row in _distance_rows(part))
    return (isinstance(constraint, Anchor | Distance),) * constraint.num_constraints


class HeatmapRegulariser(AbstractLoss):
    """Binary cross-entropy of each heatmap against a Gaussian blob at its own keypoint.

    Reconstruction alone lets a keypoint's heatmap spread over the image (its spatial softmax then
    lands between objects) or sit on the background. This term pulls each heatmap towards a single
    blob: with $h_k = e^{s_k - \\max s_k}$ the heatmap normalised to a peak of 1 (the spatial softmax
    divided by its maximum) and $g_k$ the Gaussian map (eq. 9) at the heatmap's own keypoint
    (eq. 8; a fixed target, no gradient through it),

    $$L_h = -\\operatorname{mean}_{k, p}\\big[g_k(p) \\log h_k(p) + (1 - g_k(p)) \\log(1 - h_k(p))\\big].$$

    Needs an estimator with heatmaps (`keyvision.KeypointEstimator`).

    **Arguments:**

    - `sigma`: the standard deviation of the target blobs in image-frame units (0.1, the
      renderer's, by default).

    !!! example

        ```python
        loss = keyvision.Reconstruction() + 0.01 * keyvision.HeatmapRegulariser()
        ```
    """

    sigma: float = eqx.field(static=True, default=0.1)

    def __check_init__(self):
        if not self.sigma > 0:
            raise ValueError(f"HeatmapRegulariser: sigma must be positive, got {self.sigma}")

    def __call__(self, model: KeyCLD, batch: ImageSequences) -> Array:
        if not isinstance(model.estimator, KeypointEstimator):
            raise TypeError(
                "HeatmapRegulariser needs an estimator with heatmaps (keyvision.KeypointEstimator), got "
                f"{type(model.estimator).__name__}"
            )
        images = _images(model, batch)
        if batch.transforms is not None:  # the heatmaps the estimator draws for what it sees
            images = transform_images(images, jnp.asarray(batch.transforms))
        images = images.reshape(-1, *images.shape[-3:])
        return jnp.mean(jax.vmap(lambda image: self._one(model.estimator, image))(images))

    def _one(self, estimator: KeypointEstimator, image: Array) -> Array:
        logits = estimator.heatmaps(image)
        _, height, width = logits.shape
        centres = jax.lax.stop_gradient(spatial_softmax(logits))
        target = gaussian_maps(centres, height, width, sigma=self.sigma)
        z = logits - jnp.max(logits, axis=(1, 2), keepdims=True)  # log h <= 0
        log_h = jnp.maximum(z, -100.0)
        log_one_minus_h = jnp.log(-jnp.expm1(jnp.minimum(z, -_LOG_FLOOR)))
        return -jnp.mean(target * log_h + (1 - target) * log_one_minus_h)
