"""Dihedral augmentation of the estimator's input (the authors' 2024 recipe): each frame is seen by
the keypoint estimator rotated by a multiple of 90 degrees and possibly mirrored, and its keypoints
are mapped back to the frame as it was, so reconstruction still compares with the frame itself.

The eight symmetries of a square permute its pixels exactly and map the image frame (x right, y
up, origin at the centre, see `keyvision.pixel_grid`) linearly onto itself, so the estimator is
trained to be equivariant to them at no cost in accuracy. A transform is an index `g` in `0..7`:
`g % 4` quarter turns counter-clockwise after a left-right mirror when `g >= 4`; 0 is the identity.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray, PyTree

from cldyn import AbstractBatching

NUM_TRANSFORMS = 8


def _matrices() -> np.ndarray:
    """`(8, 2, 2)`: the linear map of image-frame points under each transform."""
    quarter = np.array([[0.0, -1.0], [1.0, 0.0]])  # counter-clockwise, y up
    mirror = np.array([[-1.0, 0.0], [0.0, 1.0]])  # left-right
    turns = [np.linalg.matrix_power(quarter, k) for k in range(4)]
    return np.stack(turns + [turn @ mirror for turn in turns])


_MATRICES = _matrices()


def _transform_image(image: Array, index: int) -> Array:
    if index >= 4:
        image = image[:, ::-1]
    # np.rot90 on (row, col) turns the picture counter-clockwise as displayed (row 0 at the top)
    return jnp.rot90(image, k=index % 4, axes=(0, 1))


def transform_images(
    images: Float[Array, "*batch H W C"], transforms: Int[Array, "*batch"]
) -> Float[Array, "*batch H W C"]:
    """Each image turned and mirrored by its transform index (`0..7`; see the module docstring).

    A point at `p` in the image frame of an image lands at `M[g] @ p` in the transformed image, with
    `M[g]` a signed permutation matrix (`restore_keypoints` applies its inverse).

    **Arguments:**

    - `images`: `(..., H, W, C)` square images.
    - `transforms`: `(...)` integer transform indices.

    **Returns:** the transformed images, same shape.
    """
    images, transforms = jnp.asarray(images), jnp.asarray(transforms)
    if images.shape[-3] != images.shape[-2]:
        raise ValueError(f"transform_images: the images must be square, got {images.shape[-3:-1]}")
    lead = images.shape[:-3]
    if transforms.shape != lead:
        raise ValueError(f"transform_images: {lead} images but transforms of shape {transforms.shape}")
    flat = images.reshape(-1, *images.shape[-3:])
    branches = [lambda image, index=index: _transform_image(image, index) for index in range(NUM_TRANSFORMS)]
    out = jax.vmap(lambda image, g: jax.lax.switch(g, branches, image))(flat, transforms.reshape(-1))
    return out.reshape(images.shape)


def restore_keypoints(
    keypoints: Float[Array, "*batch K 2"], transforms: Int[Array, "*batch"]
) -> Float[Array, "*batch K 2"]:
    """Keypoints found in transformed images, mapped back to the frames as they were:
    `p = M[g]^{-1} p'` (`M[g]` orthogonal, so its transpose)."""
    matrices = jnp.asarray(_MATRICES, dtype=keypoints.dtype)[transforms]  # (..., 2, 2)
    return jnp.einsum("...ji,...kj->...ki", matrices, keypoints)


class Augment(AbstractBatching):
    """Batches with a random dihedral transform for every frame: the frames are drawn by `batching`,
    and the batch's `transforms` (an `ImageSequences` field) get indices drawn uniformly from the
    eight symmetries of the square. The image losses then encode each frame as the estimator sees
    it transformed, and map its keypoints back (`KeyCLD.encode`); reconstruction and dynamics stay
    in the frame of the untransformed images.

    **Arguments:**

    - `batching`: how the frames are drawn, e.g. `cldyn.Windows(8, 10)`.

    !!! example

        ```python
        result = cldyn.fit(model, data, loss=keyvision.Reconstruction(), steps=1000, key=key,
                           batching=keyvision.Augment(cldyn.Windows(32, 1)))
        ```
    """

    batching: AbstractBatching

    def __check_init__(self):
        if not isinstance(self.batching, AbstractBatching):
            raise TypeError(f"Augment wraps a cldyn batching, got {type(self.batching).__name__}")

    @property
    def batch_size(self) -> int:
        """The batch size of the wrapped batching."""
        return self.batching.batch_size

    def check(self, data: PyTree) -> None:
        from ._data import ImageSequences

        if not isinstance(data, ImageSequences):
            raise TypeError(f"Augment draws from keyvision.ImageSequences, got {type(data).__name__}")
        self.batching.check(data)

    def draw(self, data: PyTree, key: PRNGKeyArray) -> PyTree:
        draw_key, transform_key = jax.random.split(key)
        batch = self.batching.draw(data, draw_key)
        transforms = jax.random.randint(transform_key, batch.frames.shape[:2], 0, NUM_TRANSFORMS)
        return eqx.tree_at(
            lambda b: b.transforms, batch, transforms.astype(jnp.int32), is_leaf=lambda x: x is None
        )
