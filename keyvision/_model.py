"""KeyCLD: a keypoint estimator, any cldyn dynamics model and a renderer (paper section 3, figure 2)."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from cldyn import AbstractDynamics

from ._augment import restore_keypoints, transform_images
from ._estimator import AbstractKeypointEstimator
from ._renderer import AbstractRenderer


def parameter_dtype(module: eqx.Module):
    """The floating dtype of the first parameter of `module` (float32 if it has none)."""
    leaves = jax.tree.leaves(eqx.filter(module, eqx.is_inexact_array))
    return leaves[0].dtype if leaves else jnp.float32


class KeyCLD(eqx.Module):
    """The KeyCLD model: frames -> keypoint estimator -> Cartesian keypoints -> cldyn dynamics ->
    renderer -> frames, all learnable and trained jointly (figure 2 of the paper).

    The state of the dynamics is the flat vector of the estimated keypoints in the image frame
    (x right, y up, `[-1, 1]`), laid out `[x1, y1, x2, y2, ...]` as everywhere in cldyn; so a
    constraint such as `cldyn.Anchor(0)` anchors a keypoint to the image centre.

    **Arguments:**

    - `estimator`: an `AbstractKeypointEstimator` (`KeypointEstimator` or the FC ablation).
    - `dynamics`: any `cldyn.AbstractDynamics` with `2K` coordinates: the constrained Lagrangian of
      `cldyn.keycld_model`, its variant without constraints, or `cldyn.SecondOrderNeuralODE`.
    - `renderer`: an `AbstractRenderer` for the same `K` keypoints and image size.

    !!! example

        ```python
        keys = jax.random.split(jax.random.key(0), 3)
        model = keyvision.KeyCLD(
            keyvision.KeypointEstimator(1, width=16, key=keys[0]),
            cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=keys[1]),
            keyvision.Renderer(1, width=16, key=keys[2]),
        )
        x = model.encode(images)          # (T, 64, 64, 3) -> (T, 2)
        reconstructed = model.decode(x)   # (T, 64, 64, 3)
        ```
    """

    estimator: AbstractKeypointEstimator
    dynamics: AbstractDynamics
    renderer: AbstractRenderer

    def __check_init__(self):
        if not isinstance(self.estimator, AbstractKeypointEstimator):
            raise TypeError(f"KeyCLD: estimator must be an AbstractKeypointEstimator, got {self.estimator!r}")
        if not isinstance(self.renderer, AbstractRenderer):
            raise TypeError(f"KeyCLD: renderer must be an AbstractRenderer, got {self.renderer!r}")
        if not isinstance(self.dynamics, AbstractDynamics):
            raise TypeError(f"KeyCLD: dynamics must be a cldyn.AbstractDynamics, got {self.dynamics!r}")
        count = self.estimator.num_keypoints
        if self.renderer.num_keypoints != count or self.dynamics.size != 2 * count:
            raise ValueError(
                f"KeyCLD: the estimator gives {count} keypoints, the renderer takes "
                f"{self.renderer.num_keypoints} and the dynamics have {self.dynamics.size} coordinates "
                f"(must be {2 * count})"
            )
        if self.renderer.image_size != self.estimator.image_size:
            raise ValueError(
                f"KeyCLD: the estimator takes {self.estimator.image_size}-pixel images but the renderer "
                f"draws {self.renderer.image_size}-pixel images"
            )

    @property
    def num_keypoints(self) -> int:
        """The number `K` of keypoints."""
        return self.estimator.num_keypoints

    @property
    def image_size(self) -> int:
        """The side of the square images in pixels."""
        return self.estimator.image_size

    def encode(
        self, images: Float[Array, "*batch H W C"], transforms: Int[Array, "*batch"] | None = None
    ) -> Float[Array, "*batch k"]:
        """The keypoint state `x` (`k = 2K`) of each image (values in `[0, 1]`), any leading axes.

        **Arguments:**

        - `images`: `(..., H, W, C)`, e.g. the `T` frames of a run.
        - `transforms`: `(...)` dihedral transform indices (`keyvision.Augment`), or `None`. Each
          image is shown to the estimator transformed, and its keypoints are mapped back to the
          image as it was: an equivariant estimator gives the same keypoints either way.

        **Returns:** `(..., 2K)`: the estimator's keypoints, flattened `[x1, y1, x2, y2, ...]`.
        """
        images = jnp.asarray(images)
        lead = images.shape[:-3]
        if transforms is not None:
            transforms = jnp.asarray(transforms)
            images = transform_images(images, transforms)
        flat = images.reshape(-1, *images.shape[-3:])
        keypoints = jax.vmap(self.estimator)(flat).reshape(*lead, self.num_keypoints, 2)
        if transforms is not None:
            keypoints = restore_keypoints(keypoints, transforms)
        return keypoints.reshape(*lead, 2 * self.num_keypoints)

    def decode(self, x: Float[Array, "*batch k"]) -> Float[Array, "*batch H W 3"]:
        """The rendered image of each keypoint state, any leading axes.

        **Arguments:**

        - `x`: `(..., 2K)` keypoint states in the image frame.

        **Returns:** `(..., H, W, 3)` images with values in `(0, 1)`.
        """
        x = jnp.asarray(x)
        lead = x.shape[:-1]
        keypoints = x.reshape(-1, self.num_keypoints, 2)
        images = jax.vmap(self.renderer)(keypoints)
        return images.reshape(*lead, *images.shape[1:])
