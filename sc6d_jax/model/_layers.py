"""Small functional layers (NHWC activations, HWIO kernels): conv2d, GroupNorm, dense, upsampling.

Parameters are plain arrays; every layer is a pure function. ``conv2d`` has two
implementations that compute the same thing:

* ``"lax"``: :func:`jax.lax.conv_general_dilated`.
* ``"im2col"``: the padded input is sliced once per kernel tap (with stride and dilation),
  the taps are stacked on the channel axis and multiplied with the reshaped kernel in one
  matrix product. XLA:CPU runs this up to 10-50x faster than ``lax.conv`` on small feature
  maps (REFERENCE section 3) and faster on stride-2 3x3 convs, slower on large stride-1 maps.
* ``"auto"``: :func:`choose_conv_impl` picks per layer from the layer's shape.

A kernel may also be *per sample* (shape ``(B, kh, kw, cin, cout)``), which is how the
per-object decoders are evaluated: the object's weights are gathered for each sample.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

CONV_IMPLS = ("auto", "im2col", "lax")


def conv_output_size(size: int, kernel: int, stride: int, dilation: int) -> int:
    """Output length of a conv with symmetric padding ``dilation * (kernel - 1) // 2``."""
    pad = dilation * (kernel - 1) // 2
    return (size + 2 * pad - dilation * (kernel - 1) - 1) // stride + 1


def choose_conv_impl(
    h: int, w: int, kernel: int, stride: int, dilation: int, cin: int, per_sample: bool = False
) -> str:
    """The implementation ``conv_impl="auto"`` uses for one layer (decided at trace time).

    Measured on the project's 2-core CPU, forward + backward, batch 32, the layer shapes of a
    64x64 crop (see the model report): im2col wins on stride-2 3x3 convs (1.2-1.8x) and on
    small maps (up to 12x for a 4x4x512 input); ``lax.conv`` wins on stride-1 maps of 16x16
    and larger (1.5-3x: the stacked patch matrix costs more memory traffic than it saves) and
    on the 7x7 stem (2x). Per-sample kernels (per-object decoders) always use im2col: a
    batched matrix product instead of XLA's grouped convolution.
    """
    del cin, dilation
    if kernel == 1 or per_sample:
        return "im2col"
    ho = conv_output_size(h, kernel, stride, 1)
    wo = conv_output_size(w, kernel, stride, 1)
    if ho * wo <= 16:
        return "im2col"
    if kernel <= 3 and (stride > 1 or ho * wo <= 64):
        return "im2col"
    return "lax"


def _pad_hw(x: jax.Array, pad: int) -> jax.Array:
    if pad == 0:
        return x
    return jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))


def im2col(x: jax.Array, kernel: int, stride: int, dilation: int) -> jax.Array:
    """Patches of ``x`` (B,H,W,C) -> (B,Ho,Wo,kernel*kernel*C), tap-major then channel.

    Padding is symmetric, ``dilation * (kernel - 1) // 2`` (PyTorch's ``padding=dilation``
    for 3x3 kernels), so the patch order matches an HWIO kernel reshaped to (kh*kw*cin, cout).
    """
    b, h, w, c = x.shape
    pad = dilation * (kernel - 1) // 2
    ho = conv_output_size(h, kernel, stride, dilation)
    wo = conv_output_size(w, kernel, stride, dilation)
    xp = _pad_hw(x, pad)
    if kernel == 1 and stride == 1:
        return xp
    taps = []
    for i in range(kernel):
        for j in range(kernel):
            r0, c0 = i * dilation, j * dilation
            taps.append(
                lax.slice(
                    xp,
                    (0, r0, c0, 0),
                    (b, r0 + (ho - 1) * stride + 1, c0 + (wo - 1) * stride + 1, c),
                    (1, stride, stride, 1),
                )
            )
    if len(taps) == 1:
        return taps[0]
    return jnp.concatenate(taps, axis=-1)


def conv2d(
    x: jax.Array,
    w: jax.Array,
    b: jax.Array | None = None,
    *,
    stride: int = 1,
    dilation: int = 1,
    impl: str = "auto",
) -> jax.Array:
    """2-D convolution, NHWC input, HWIO kernel (or per-sample (B,kh,kw,cin,cout)), square odd kernels.

    Padding is symmetric ``dilation * (k - 1) // 2`` on both spatial axes, so a stride-1 conv
    keeps the size and a stride-2 conv halves an even size.
    """
    if impl not in CONV_IMPLS:
        raise ValueError(f"conv impl must be one of {CONV_IMPLS}, got {impl!r}")
    per_sample = w.ndim == 5
    kh, kw, cin, cout = w.shape[-4:]
    if kh != kw or kh % 2 != 1:
        raise ValueError(f"conv2d supports square odd kernels only, got {kh}x{kw}")
    if x.shape[-1] != cin:
        raise ValueError(f"conv2d: input has {x.shape[-1]} channels, kernel expects {cin}")
    if impl == "auto":
        impl = choose_conv_impl(x.shape[1], x.shape[2], kh, stride, dilation, cin, per_sample)
    if impl == "im2col":
        patches = im2col(x, kh, stride, dilation)
        if per_sample:
            y = jnp.einsum("bhwk,bko->bhwo", patches, w.reshape(w.shape[0], kh * kw * cin, cout))
        else:
            y = patches @ w.reshape(kh * kw * cin, cout)
    else:
        pad = dilation * (kh - 1) // 2

        def one(xi: jax.Array, wi: jax.Array) -> jax.Array:
            return lax.conv_general_dilated(
                xi,
                wi,
                window_strides=(stride, stride),
                padding=((pad, pad), (pad, pad)),
                rhs_dilation=(dilation, dilation),
                dimension_numbers=("NHWC", "HWIO", "NHWC"),
            )

        if per_sample:
            y = jax.vmap(lambda xi, wi: one(xi[None], wi)[0])(x, w)
        else:
            y = one(x, w)
    if b is not None:
        y = y + (b[:, None, None, :] if b.ndim == 2 else b)
    return y


def num_groups(channels: int, max_groups: int) -> int:
    """Largest group count <= ``max_groups`` that divides ``channels`` (GroupNorm(32) when possible)."""
    g = max(1, min(max_groups, channels))
    while channels % g:
        g -= 1
    return g


def group_norm(
    x: jax.Array, scale: jax.Array, bias: jax.Array, groups: int, eps: float = 1e-5
) -> jax.Array:
    """GroupNorm over (spatial..., channels-in-group) of NHWC or (B,C) input.

    ``scale``/``bias`` are (C,) or per sample (B,C).

    One pass over ``x`` for the statistics (its mean and mean square, var = E[x^2] - E[x]^2),
    and the normalisation folded with ``scale``/``bias`` into one affine per sample and
    channel, ``y = x a + b``: XLA fuses the two reductions and the forward and backward
    passes read the activations less often than the textbook form (1.4-2.7x faster forward
    and backward on CPU at the presets' shapes; experiments/bench_group_norm.py).
    """
    c = x.shape[-1]
    if c % groups:
        raise ValueError(f"group_norm: {c} channels not divisible by {groups} groups")
    shape = x.shape
    B, cg = shape[0], c // groups
    xg = x.reshape(B, -1, groups, cg)
    mean = jnp.mean(xg, axis=(1, 3), keepdims=True)
    msq = jnp.mean(jnp.square(xg), axis=(1, 3), keepdims=True)
    inv = lax.rsqrt(jnp.maximum(msq - jnp.square(mean), 0.0) + eps)
    lead = scale.shape[0] if scale.ndim == 2 else 1
    a = inv * scale.reshape(lead, 1, groups, cg)
    b = bias.reshape(lead, 1, groups, cg) - mean * a
    return (xg * a + b).reshape(shape)


def dense(x: jax.Array, w: jax.Array, b: jax.Array | None = None) -> jax.Array:
    """``x @ w + b``; ``w`` (in,out) shared or (B,in,out) per sample (then x is (B,...,in))."""
    if w.ndim == 3:
        if x.ndim == 2:
            y = jnp.einsum("bi,bio->bo", x, w)
        else:
            y = jnp.einsum("b...i,bio->b...o", x, w)
    else:
        y = x @ w
    if b is not None:
        if b.ndim == 2 and y.ndim > 2:
            b = b.reshape(b.shape[0], *((1,) * (y.ndim - 2)), b.shape[-1])
        y = y + b
    return y


def upsample2x_bilinear(x: jax.Array) -> jax.Array:
    """2x bilinear upsampling of NHWC input, half-pixel centres with edge clamping.

    Same values as PyTorch's ``nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False)``.
    """

    def along(a: jax.Array, axis: int) -> jax.Array:
        n = a.shape[axis]
        prev = jnp.concatenate([lax.slice_in_dim(a, 0, 1, axis=axis), lax.slice_in_dim(a, 0, n - 1, axis=axis)], axis)
        nxt = jnp.concatenate([lax.slice_in_dim(a, 1, n, axis=axis), lax.slice_in_dim(a, n - 1, n, axis=axis)], axis)
        even = 0.75 * a + 0.25 * prev
        odd = 0.75 * a + 0.25 * nxt
        out = jnp.stack([even, odd], axis=axis + 1)
        new_shape = list(a.shape)
        new_shape[axis] = 2 * n
        return out.reshape(new_shape)

    return along(along(x, 1), 2)


# ----------------------------------------------------------------------------- initialisers


# Initialisation draws from a numpy Generator seeded by the JAX key: building a model's
# hundreds of parameter arrays that way takes milliseconds, where dispatching (or compiling)
# as many jax.random calls takes seconds to tens of seconds on a CPU. Same key -> same
# Generator stream -> bit-identical params.


def make_rng(key: jax.Array) -> np.random.Generator:
    """numpy Generator seeded from a JAX PRNG key (typed ``jax.random.key`` or raw uint32)."""
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    words = [int(v) for v in np.asarray(key, dtype=np.uint32).ravel()]
    return np.random.default_rng(words)


def split(rng: np.random.Generator, n: int) -> list[np.random.Generator]:
    """``n`` independent child generators (``Generator.spawn``)."""
    return rng.spawn(n)


def normal(rng: np.random.Generator, shape: tuple[int, ...], std: float) -> np.ndarray:
    """float32 normal draws with standard deviation ``std``."""
    return (rng.standard_normal(shape, dtype=np.float32) * np.float32(std)).astype(np.float32)


def stack_trees(trees: list) -> dict:
    """Stack a list of identical param trees on a new leading axis (per-object params)."""
    return jax.tree.map(lambda *xs: np.stack(xs), *trees)


def he_normal(rng: np.random.Generator, shape: tuple[int, ...], fan_in: int) -> np.ndarray:
    """He (Kaiming) normal initialisation for ReLU layers: std = sqrt(2 / fan_in)."""
    return normal(rng, shape, math.sqrt(2.0 / fan_in))


def init_conv(key: np.random.Generator, k: int, cin: int, cout: int, bias: bool = False) -> dict:
    """Params of a k x k conv: {'w': (k,k,cin,cout)} plus {'b': (cout,)} when ``bias``."""
    p = {"w": he_normal(key, (k, k, cin, cout), k * k * cin)}
    if bias:
        p["b"] = np.zeros((cout,), np.float32)
    return p


def init_dense(key: np.random.Generator, cin: int, cout: int, scale: float = 2.0) -> dict:
    """Params of a dense layer: {'w': (cin,cout) normal std sqrt(scale/cin), 'b': zeros}."""
    return {"w": normal(key, (cin, cout), math.sqrt(scale / cin)), "b": np.zeros((cout,), np.float32)}


def init_gn(c: int) -> dict:
    """GroupNorm params: scale ones, bias zeros."""
    return {"scale": np.ones((c,), np.float32), "bias": np.zeros((c,), np.float32)}
