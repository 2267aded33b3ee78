"""Keypoint estimators: an image in, Cartesian keypoints in the image frame out (paper section 3, A.4)."""

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from cldyn._misc import check_positive
from cldyn._nn import linear

from ._keypoints import check_order, spatial_softmax, unpermuted
from ._unet import Block, UNet, max_pool


def _check_sizes(owner: str, num_keypoints: int, width: int, image_size: int, multiple: int) -> None:
    check_positive(f"{owner}: num_keypoints", num_keypoints, integer=True)
    check_positive(f"{owner}: width", width, integer=True)
    check_positive(f"{owner}: image_size", image_size, integer=True)
    if image_size % multiple:
        raise ValueError(f"{owner}: image_size must be a multiple of {multiple}, got {image_size}")


def _channels_first(owner: str, image: Array, image_size: int, channels: int) -> Array:
    if image.shape != (image_size, image_size, channels):
        raise ValueError(
            f"{owner} takes one image of shape ({image_size}, {image_size}, {channels}) (vmap for a "
            f"batch), got {image.shape}"
        )
    return jnp.moveaxis(image, -1, 0)


class AbstractKeypointEstimator(eqx.Module):
    """Maps one image `(H, W, C)` with values in `[0, 1]` to `K` keypoints `(K, 2)` in the image frame
    (x right, y up, `[-1, 1]`; see `keyvision.pixel_grid`). Batch with `jax.vmap`."""

    num_keypoints: eqx.AbstractVar[int]
    image_size: eqx.AbstractVar[int]

    @abc.abstractmethod
    def __call__(self, image: Float[Array, "H W C"]) -> Float[Array, "K 2"]:
        """The keypoints of one image."""

    def permute(self, order: Sequence[int]) -> "AbstractKeypointEstimator":
        """The same estimator with its keypoints renumbered: keypoint `k` of the result is keypoint
        `order[k]` of this one, for every image.

        `keyvision.assign_keypoints` calls it; the identity order returns the estimator itself, and a
        subclass that does not override it cannot be renumbered (a `NotImplementedError` says so)."""
        return unpermuted(self, order)


class KeypointEstimator(AbstractKeypointEstimator):
    """The paper's fully convolutional keypoint estimator: a U-Net (appendix A.4) gives one heatmap per
    keypoint and the spatial softmax (eq. 8) turns each into a point.

    Being convolutional, it is equivariant to translations: a picture shifted by `k` pixels gives
    keypoints shifted by `2k / image_size` (away from the borders).

    **Arguments:**

    - `num_keypoints`: the number `K` of keypoints.
    - `width`: the width `w` of the U-Net (blocks of `w, 2w, 4w` channels; 32 in the paper).
    - `image_size`: the side of the square input images in pixels (a multiple of 4; 64 in the
      paper).
    - `channels`: the number of colour channels of the input (3 for RGB).
    - `dtype`: the floating-point type of the parameters (float32 by default).
    - `key`: a `jax.random` key (keyword-only).

    !!! example

        ```python
        estimator = keyvision.KeypointEstimator(2, width=16, key=jax.random.key(0))
        keypoints = jax.vmap(estimator)(images)       # images (B, 64, 64, 3) -> (B, 2, 2)
        ```
    """

    unet: UNet
    num_keypoints: int = eqx.field(static=True)
    image_size: int = eqx.field(static=True)
    channels: int = eqx.field(static=True)

    def __init__(
        self,
        num_keypoints: int,
        *,
        width: int = 32,
        image_size: int = 64,
        channels: int = 3,
        dtype=jnp.float32,
        key: PRNGKeyArray,
    ):
        _check_sizes("KeypointEstimator", num_keypoints, width, image_size, 4)
        check_positive("KeypointEstimator: channels", channels, integer=True)
        self.unet = UNet(channels, num_keypoints, width, dtype=dtype, key=key)
        self.num_keypoints = num_keypoints
        self.image_size = image_size
        self.channels = channels

    def heatmaps(self, image: Float[Array, "H W C"]) -> Float[Array, "K H W"]:
        """The unnormalised heatmaps (logits `s_k` of eq. 8) of one image, channels-first."""
        return self.unet(_channels_first("KeypointEstimator", image, self.image_size, self.channels))

    def __call__(self, image: Float[Array, "H W C"]) -> Float[Array, "K 2"]:
        """The keypoints `(K, 2)` of one image `(H, W, C)`: `spatial_softmax(self.heatmaps(image))`."""
        return spatial_softmax(self.heatmaps(image))

    def permute(self, order: Sequence[int]) -> "KeypointEstimator":
        """See `AbstractKeypointEstimator.permute`: the heatmaps' output channels, reordered."""
        index = check_order("KeypointEstimator", order, self.num_keypoints)
        head = self.unet.head
        return eqx.tree_at(
            lambda e: (e.unet.head.weight, e.unet.head.bias), self, (head.weight[index], head.bias[index])
        )


class KeypointEstimatorFC(AbstractKeypointEstimator):
    """The FC ablation of appendix A.4: four convolution blocks (widths `w, 2w, 4w, 8w`), each followed
    by 2x2 max-pooling, then fully connected layers (256 units, ReLU) regress the `2K` coordinates
    directly. Not translation equivariant: the ablation shows what the spatial softmax brings.

    **Arguments:** as `KeypointEstimator`; `image_size` must be a multiple of 16, and `hidden` is
    the width of the fully connected layer.

    !!! example

        ```python
        estimator = keyvision.KeypointEstimatorFC(2, width=16, key=jax.random.key(0))
        ```
    """

    blocks: tuple[Block, ...]
    hidden: eqx.nn.Linear
    output: eqx.nn.Linear
    num_keypoints: int = eqx.field(static=True)
    image_size: int = eqx.field(static=True)
    channels: int = eqx.field(static=True)

    def __init__(
        self,
        num_keypoints: int,
        *,
        width: int = 32,
        image_size: int = 64,
        channels: int = 3,
        hidden: int = 256,
        dtype=jnp.float32,
        key: PRNGKeyArray,
    ):
        _check_sizes("KeypointEstimatorFC", num_keypoints, width, image_size, 16)
        check_positive("KeypointEstimatorFC: hidden", hidden, integer=True)
        keys = jax.random.split(key, 6)
        sizes = (channels, width, 2 * width, 4 * width, 8 * width)
        self.blocks = tuple(Block(sizes[i], sizes[i + 1], dtype=dtype, key=keys[i]) for i in range(4))
        flat = 8 * width * (image_size // 16) ** 2
        self.hidden = linear(flat, hidden, dtype=dtype, key=keys[4])
        self.output = linear(hidden, 2 * num_keypoints, dtype=dtype, key=keys[5])
        self.num_keypoints = num_keypoints
        self.image_size = image_size
        self.channels = channels

    def __call__(self, image: Float[Array, "H W C"]) -> Float[Array, "K 2"]:
        """The keypoints `(K, 2)` of one image `(H, W, C)`."""
        x = _channels_first("KeypointEstimatorFC", image, self.image_size, self.channels)
        for block in self.blocks:
            x = max_pool(block(x))
        x = jax.nn.relu(self.hidden(x.reshape(-1)))
        return self.output(x).reshape(self.num_keypoints, 2)

    def permute(self, order: Sequence[int]) -> "KeypointEstimatorFC":
        """See `AbstractKeypointEstimator.permute`: the output layer's rows, reordered in pairs."""
        index = check_order("KeypointEstimatorFC", order, self.num_keypoints)
        rows = (2 * index[:, None] + jnp.arange(2)[None, :]).reshape(-1)
        weight, bias = self.output.weight[rows], self.output.bias[rows]
        return eqx.tree_at(lambda e: (e.output.weight, e.output.bias), self, (weight, bias))
