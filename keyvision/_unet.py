"""The convolutional building blocks of KeyCLD's networks (appendix A.4), channels-first.

Channels-first (`(C, H, W)`, Equinox's `Conv2d`) was measured faster than channels-last on the CPUs
this was written on: see `benchmarks/vision_layout.py` and `benchmarks/results/vision_layout.json`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from cldyn._nn import conv2d

_GROUPS = 8  # GroupNorm(8) of appendix A.4


def max_pool(x: Float[Array, "C H W"]) -> Float[Array, "C H/2 W/2"]:
    """2x2 max pooling with stride 2 (a reshape: cheaper on CPU than a reduce-window)."""
    channels, height, width = x.shape
    return x.reshape(channels, height // 2, 2, width // 2, 2).max(axis=(2, 4))


def upsample(x: Float[Array, "C H W"]) -> Float[Array, "C 2*H 2*W"]:
    """2x nearest-neighbour upsampling: every pixel becomes a 2x2 block."""
    return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)


class Block(eqx.Module):
    """conv 3x3 (same padding) -> GroupNorm(8) -> ReLU: the `Block` of appendix A.4."""

    conv: eqx.nn.Conv2d
    norm: eqx.nn.GroupNorm

    def __init__(self, in_channels: int, out_channels: int, *, dtype, key: PRNGKeyArray):
        self.conv = conv2d(in_channels, out_channels, 3, padding=1, dtype=dtype, key=key)
        # Narrow blocks (fewer than 8 channels) normalise each channel on its own.
        self.norm = eqx.nn.GroupNorm(min(_GROUPS, out_channels), out_channels, dtype=dtype)

    def __call__(self, x: Float[Array, "C H W"]) -> Float[Array, "C2 H W"]:
        return jax.nn.relu(self.norm(self.conv(x)))


class UNet(eqx.Module):
    """The U-Net of appendix A.4: blocks of widths `w, 2w, 4w` with max-pooling on the way down,
    nearest upsampling on the way up and skip concatenations, then a 3x3 convolution to
    `out_channels`. Spatial sizes must be divisible by 4."""

    down1: Block
    down2: Block
    bottom: Block
    up2: Block
    up1: Block
    head: eqx.nn.Conv2d

    def __init__(self, in_channels: int, out_channels: int, width: int, *, dtype, key: PRNGKeyArray):
        keys = jax.random.split(key, 6)
        self.down1 = Block(in_channels, width, dtype=dtype, key=keys[0])
        self.down2 = Block(width, 2 * width, dtype=dtype, key=keys[1])
        self.bottom = Block(2 * width, 4 * width, dtype=dtype, key=keys[2])
        self.up2 = Block(6 * width, 2 * width, dtype=dtype, key=keys[3])
        self.up1 = Block(3 * width, width, dtype=dtype, key=keys[4])
        self.head = conv2d(width, out_channels, 3, padding=1, dtype=dtype, key=keys[5])

    def __call__(self, x: Float[Array, "C H W"]) -> Float[Array, "C2 H W"]:
        x1 = self.down1(x)
        x2 = self.down2(max_pool(x1))
        x3 = self.bottom(max_pool(x2))
        x4 = self.up2(jnp.concatenate([upsample(x3), x2], axis=0))
        x5 = self.up1(jnp.concatenate([upsample(x4), x1], axis=0))
        return self.head(x5)
