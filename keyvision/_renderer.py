"""Renderers: Cartesian keypoints in the image frame in, one image out (paper section 3, A.4)."""

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from cldyn._misc import check_positive
from cldyn._nn import conv2d, linear

from ._keypoints import check_order, gaussian_maps, unpermuted
from ._unet import Block, UNet, upsample

_CONSTANT_STD = 0.01  # initial scale of the learned constant feature tensor


def _check_keypoints(owner: str, keypoints: Array, num_keypoints: int) -> None:
    if keypoints.shape != (num_keypoints, 2):
        raise ValueError(
            f"{owner} takes the keypoints of one image, shape ({num_keypoints}, 2) (vmap for a batch), "
            f"got {keypoints.shape}"
        )


class AbstractRenderer(eqx.Module):
    """Maps `K` keypoints `(K, 2)` in the image frame to one image `(H, W, 3)` with values in
    `(0, 1)`. Batch with `jax.vmap`."""

    num_keypoints: eqx.AbstractVar[int]
    image_size: eqx.AbstractVar[int]

    @abc.abstractmethod
    def __call__(self, keypoints: Float[Array, "K 2"]) -> Float[Array, "H W 3"]:
        """The image of one set of keypoints."""

    def permute(self, order: Sequence[int]) -> "AbstractRenderer":
        """The same renderer for renumbered keypoints: the result draws `keypoints` as this one
        draws them with keypoint `order[k]` at `keypoints[k]` (pairs with
        `AbstractKeypointEstimator.permute`).

        The identity order returns the renderer itself; a subclass that does not override it cannot
        be renumbered (a `NotImplementedError` says so)."""
        return unpermuted(self, order)


class Renderer(AbstractRenderer):
    """The paper's renderer: each keypoint becomes a Gaussian map (eq. 9), the maps are concatenated
    with a learned constant feature tensor (which can hold the static background), and a U-Net
    (appendix A.4) followed by a sigmoid produces the RGB image.

    **Arguments:**

    - `num_keypoints`: the number `K` of keypoints.
    - `width`: the width `w` of the U-Net (32 in the paper).
    - `image_size`: the side of the square output images in pixels (a multiple of 4).
    - `sigma`: the standard deviation of the Gaussian maps in image-frame units (0.1 in the paper).
    - `constant_channels`: channels of the learned constant tensor; by default `w - K` (at least
      1), so that the U-Net's input has `w` channels.
    - `dtype`: the floating-point type of the parameters (float32 by default).
    - `key`: a `jax.random` key (keyword-only).

    !!! example

        ```python
        renderer = keyvision.Renderer(2, width=16, key=jax.random.key(1))
        images = jax.vmap(renderer)(keypoints)      # (B, 2, 2) -> (B, 64, 64, 3)
        ```
    """

    constant: Float[Array, "C H W"]
    unet: UNet
    num_keypoints: int = eqx.field(static=True)
    image_size: int = eqx.field(static=True)
    sigma: float = eqx.field(static=True)

    def __init__(
        self,
        num_keypoints: int,
        *,
        width: int = 32,
        image_size: int = 64,
        sigma: float = 0.1,
        constant_channels: int | None = None,
        dtype=jnp.float32,
        key: PRNGKeyArray,
    ):
        check_positive("Renderer: num_keypoints", num_keypoints, integer=True)
        check_positive("Renderer: width", width, integer=True)
        check_positive("Renderer: image_size", image_size, integer=True)
        check_positive("Renderer: sigma", sigma)
        if image_size % 4:
            raise ValueError(f"Renderer: image_size must be a multiple of 4, got {image_size}")
        if constant_channels is None:
            constant_channels = max(1, width - num_keypoints)
        check_positive("Renderer: constant_channels", constant_channels, integer=True)
        constant_key, unet_key = jax.random.split(key)
        self.constant = _CONSTANT_STD * jax.random.normal(
            constant_key, (constant_channels, image_size, image_size), dtype
        )
        self.unet = UNet(constant_channels + num_keypoints, 3, width, dtype=dtype, key=unet_key)
        self.num_keypoints = num_keypoints
        self.image_size = image_size
        self.sigma = float(sigma)

    def __call__(self, keypoints: Float[Array, "K 2"]) -> Float[Array, "H W 3"]:
        """The image `(H, W, 3)` of one set of keypoints `(K, 2)`."""
        _check_keypoints("Renderer", keypoints, self.num_keypoints)
        size = self.image_size
        maps = gaussian_maps(keypoints.astype(self.constant.dtype), size, size, sigma=self.sigma)
        x = self.unet(jnp.concatenate([self.constant, maps], axis=0))
        return jnp.moveaxis(jax.nn.sigmoid(x), 0, -1)

    def permute(self, order: Sequence[int]) -> "Renderer":
        """See `AbstractRenderer.permute`: the first convolution's inputs from the maps, reordered."""
        index = check_order("Renderer", order, self.num_keypoints)
        channels = self.constant.shape[0]
        weight = self.unet.down1.conv.weight
        weight = weight.at[:, channels : channels + self.num_keypoints].set(weight[:, channels + index])
        return eqx.tree_at(lambda r: r.unet.down1.conv.weight, self, weight)


class RendererFC(AbstractRenderer):
    """The FC ablation of appendix A.4: fully connected layers (256 units, ReLU) map the `2K`
    coordinates to a `8w x s x s` tensor (`s = image_size / 16`), then four blocks (widths
    `8w, 4w, 2w, w`), each followed by 2x nearest upsampling, a 3x3 convolution to RGB and a sigmoid.

    **Arguments:** as `Renderer`, without `sigma` and `constant_channels`; `image_size` must be a
    multiple of 16, and `hidden` is the width of the fully connected layer.

    !!! example

        ```python
        renderer = keyvision.RendererFC(2, width=16, key=jax.random.key(1))
        ```
    """

    hidden: eqx.nn.Linear
    expand: eqx.nn.Linear
    blocks: tuple[Block, ...]
    head: eqx.nn.Conv2d
    num_keypoints: int = eqx.field(static=True)
    image_size: int = eqx.field(static=True)
    width: int = eqx.field(static=True)

    def __init__(
        self,
        num_keypoints: int,
        *,
        width: int = 32,
        image_size: int = 64,
        hidden: int = 256,
        dtype=jnp.float32,
        key: PRNGKeyArray,
    ):
        check_positive("RendererFC: num_keypoints", num_keypoints, integer=True)
        check_positive("RendererFC: width", width, integer=True)
        check_positive("RendererFC: image_size", image_size, integer=True)
        check_positive("RendererFC: hidden", hidden, integer=True)
        if image_size % 16:
            raise ValueError(f"RendererFC: image_size must be a multiple of 16, got {image_size}")
        keys = jax.random.split(key, 7)
        start = image_size // 16
        self.hidden = linear(2 * num_keypoints, hidden, dtype=dtype, key=keys[0])
        self.expand = linear(hidden, 8 * width * start**2, dtype=dtype, key=keys[1])
        sizes = (8 * width, 8 * width, 4 * width, 2 * width, width)
        self.blocks = tuple(Block(sizes[i], sizes[i + 1], dtype=dtype, key=keys[2 + i]) for i in range(4))
        self.head = conv2d(width, 3, 3, padding=1, dtype=dtype, key=keys[6])
        self.num_keypoints = num_keypoints
        self.image_size = image_size
        self.width = width

    def __call__(self, keypoints: Float[Array, "K 2"]) -> Float[Array, "H W 3"]:
        """The image `(H, W, 3)` of one set of keypoints `(K, 2)`."""
        _check_keypoints("RendererFC", keypoints, self.num_keypoints)
        start = self.image_size // 16
        x = jax.nn.relu(self.hidden(keypoints.reshape(-1).astype(self.hidden.weight.dtype)))
        x = self.expand(x).reshape(8 * self.width, start, start)
        for block in self.blocks:
            x = upsample(block(x))
        return jnp.moveaxis(jax.nn.sigmoid(self.head(x)), 0, -1)

    def permute(self, order: Sequence[int]) -> "RendererFC":
        """See `AbstractRenderer.permute`: the first layer's columns, reordered in pairs."""
        index = check_order("RendererFC", order, self.num_keypoints)
        columns = (2 * index[:, None] + jnp.arange(2)[None, :]).reshape(-1)
        return eqx.tree_at(lambda r: r.hidden.weight, self, self.hidden.weight[:, columns])
