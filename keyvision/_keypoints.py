"""Keypoints in the image frame: spatial softmax (eq. 8), Gaussian maps (eq. 9), pixel <-> frame.

The image frame is Cartesian: `x` points right, `y` points up, the origin is the image centre and
the image spans `[-1, 1]` along both axes (for a square image). Pixel `(row, col)` of an `H x W`
image covers a cell of size `2/W x 2/H`; its centre lies at

$$x = \\frac{2\\,\\mathrm{col} + 1}{W} - 1, \\qquad y = 1 - \\frac{2\\,\\mathrm{row} + 1}{H},$$

so row 0 is the top row of the image and column 0 its left column. Heatmaps are channels-first,
`(num_keypoints, H, W)`, with rows and columns as in the image.
"""

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


def pixel_grid(height: int, width: int, *, dtype=jnp.float32) -> Float[Array, "H W 2"]:
    """The image-frame coordinates `(x, y)` of every pixel centre.

    **Arguments:**

    - `height`, `width`: the image size in pixels.
    - `dtype`: the floating-point type of the result.

    **Returns:** an array `(H, W, 2)`: `grid[row, col] = (x, y)` of that pixel's centre.

    !!! example

        ```python
        grid = keyvision.pixel_grid(64, 64)
        grid[0, 0]    # (-63/64, 63/64): the centre of the top-left pixel
        ```
    """
    xs = (2 * jnp.arange(width, dtype=dtype) + 1) / width - 1
    ys = 1 - (2 * jnp.arange(height, dtype=dtype) + 1) / height
    return jnp.stack(jnp.meshgrid(xs, ys, indexing="xy"), axis=-1)


def pixel_to_frame(pixels: Float[ArrayLike, "*batch 2"], height: int, width: int) -> Float[Array, "*batch 2"]:
    """Image-frame coordinates `(x, y)` of continuous pixel coordinates `(row, col)`.

    Integer `(row, col)` is the centre of that pixel; `(-0.5, -0.5)` is the top-left corner of the
    image, which maps to `(-1, 1)`.

    **Arguments:**

    - `pixels`: `(..., 2)` pixel coordinates `(row, col)`.
    - `height`, `width`: the image size in pixels.

    **Returns:** `(..., 2)` points `(x, y)` in the image frame.

    !!! example

        ```python
        keyvision.pixel_to_frame(jnp.array([31.5, 31.5]), 64, 64)   # (0, 0): the image centre
        ```
    """
    pixels = jnp.asarray(pixels)
    row, col = pixels[..., 0], pixels[..., 1]
    return jnp.stack([(2 * col + 1) / width - 1, 1 - (2 * row + 1) / height], axis=-1)


def frame_to_pixel(points: Float[ArrayLike, "*batch 2"], height: int, width: int) -> Float[Array, "*batch 2"]:
    """Continuous pixel coordinates `(row, col)` of image-frame points `(x, y)`: the inverse of
    `pixel_to_frame`.

    **Arguments:**

    - `points`: `(..., 2)` points `(x, y)` in the image frame.
    - `height`, `width`: the image size in pixels.

    **Returns:** `(..., 2)` pixel coordinates `(row, col)`; rounding them gives the pixel that
    contains the point.

    !!! example

        ```python
        keyvision.frame_to_pixel(jnp.array([-1.0, 1.0]), 64, 64)   # (-0.5, -0.5): top-left corner
        ```
    """
    points = jnp.asarray(points)
    x, y = points[..., 0], points[..., 1]
    return jnp.stack([((1 - y) * height - 1) / 2, ((x + 1) * width - 1) / 2], axis=-1)


def spatial_softmax(logits: Float[Array, "K H W"]) -> Float[Array, "K 2"]:
    """Keypoints as the expected pixel position under the softmax of each heatmap (eq. 8).

    $$x_k = \\frac{\\sum_p x_p\\, e^{s_k(p)}}{\\sum_p e^{s_k(p)}}$$

    over the pixel centres `x_p` of the image frame. The maximum logit of each heatmap is subtracted
    before exponentiating (softmax is invariant to it), so arbitrarily large logits stay finite.

    **Arguments:**

    - `logits`: `(K, H, W)` unnormalised heatmaps `s_k`, one per keypoint.

    **Returns:** `(K, 2)` keypoints `(x, y)` in the image frame, inside `[-1, 1]^2`.

    !!! example

        ```python
        logits = jnp.zeros((1, 64, 64)).at[0, 10, 40].set(1e4)
        keyvision.spatial_softmax(logits)   # the centre of pixel (10, 40): (0.265625, 0.671875)
        ```
    """
    num, height, width = logits.shape
    flat = logits.reshape(num, height * width)
    weights = jax.nn.softmax(flat, axis=-1)  # subtracts the maximum
    grid = pixel_grid(height, width, dtype=weights.dtype).reshape(height * width, 2)
    return weights @ grid


def gaussian_maps(
    keypoints: Float[Array, "K 2"], height: int, width: int, *, sigma: float
) -> Float[Array, "K H W"]:
    """Gaussian blobs centred on the keypoints (eq. 9), one map per keypoint.

    $$s'_k(p) = \\exp\\left(-\\frac{\\lVert x_p - x_k \\rVert^2}{2 \\sigma^2}\\right)$$

    with `x_p` the pixel centres of the image frame; the peak value is 1 at the keypoint.

    **Arguments:**

    - `keypoints`: `(K, 2)` points `(x, y)` in the image frame.
    - `height`, `width`: the size of the maps in pixels.
    - `sigma`: the standard deviation of the blobs in image-frame units (the image is 2 wide); the
      paper uses 0.1.

    **Returns:** `(K, H, W)` maps with values in `(0, 1]`, in the dtype of `keypoints`.

    !!! example

        ```python
        maps = keyvision.gaussian_maps(jnp.zeros((2, 2)), 64, 64, sigma=0.1)   # (2, 64, 64)
        ```
    """
    grid = pixel_grid(height, width, dtype=keypoints.dtype)
    offsets = grid[None, :, :, :] - keypoints[:, None, None, :]
    return jnp.exp(-jnp.sum(offsets**2, axis=-1) / (2 * sigma**2))


def check_order(owner: str, order: Sequence[int], num_keypoints: int) -> Array:
    """`order` as an index array, or a `ValueError` if it is not a permutation of the keypoints."""
    index = np.asarray(order, dtype=int).reshape(-1)
    if sorted(index.tolist()) != list(range(num_keypoints)):
        raise ValueError(
            f"{owner}.permute: order must be a permutation of 0..{num_keypoints - 1}, got {list(order)}"
        )
    return jnp.asarray(index)


def unpermuted(module, order: Sequence[int]):
    """`module` itself where `order` is the identity; a `NotImplementedError` naming its class
    otherwise: the default `permute` of a network that cannot renumber its keypoints."""
    index = check_order(type(module).__name__, order, module.num_keypoints)
    if np.array_equal(np.asarray(index), np.arange(module.num_keypoints)):
        return module
    raise NotImplementedError(
        f"{type(module).__name__} does not implement permute(order): its keypoints cannot be renumbered "
        f"to {list(order)}; implement it, or order the constraints as the estimator found the keypoints"
    )
