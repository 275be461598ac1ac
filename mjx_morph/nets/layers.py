"""Building blocks with PyTorch's default initialisation.

- `TorchLinear`: ``y = x @ kernel + bias`` with PyTorch's `nn.Linear` defaults, kernel and bias both
  U(-1/sqrt(fan_in), 1/sqrt(fan_in)) (kaiming-uniform with a=sqrt(5) reduces to that bound), unless an
  initialiser is given.
- `MLP`: a stack of `TorchLinear` with ReLU between layers (and optionally after the last one).
- `EncoderLayer`: one pre-norm transformer encoder layer, either ordinary self-attention with a key mask
  (MetaMorph) or fixed attention whose queries and keys come from the context only (ModuMorph). The
  attention has PyTorch `nn.MultiheadAttention`'s parameters: a packed q/k/v projection (xavier-uniform on
  the packed 3D x D matrix, zero bias) and an output projection (default Linear weight, zero bias), so its
  count is 4 D^2 + 4 D (66,048 for D = 128), equal to Flax's MHA.

Parameters are float32; `dtype` (None: float32, as the original code) is the compute dtype: each layer casts its
parameters and its input to it where it uses them (precision.py says what stays float32). No dropout (MetaMorph* and
ModuMorph run with dropout 0).
"""
from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

Initializer = Callable[..., jax.Array]
Dtype = Any

LN_EPS = 1e-5  # PyTorch's LayerNorm default (Flax's is 1e-6)


def uniform(bound: float) -> Initializer:
    """U(-bound, bound)."""
    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)
    return init


zeros = nn.initializers.zeros


def cast(dtype: Dtype, *xs: jax.Array):
    """The arrays in the compute dtype (unchanged when it is None)."""
    return xs if dtype is None else tuple(jnp.asarray(x, dtype) for x in xs)


class TorchLinear(nn.Module):
    """`nn.Linear` with PyTorch's default initialisation unless `kernel_init` / `bias_init` are given."""
    features: int
    kernel_init: Initializer | None = None
    bias_init: Initializer | None = None
    dtype: Dtype = None

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        fan_in = x.shape[-1]
        default = uniform(1.0 / math.sqrt(fan_in))
        kernel = self.param("kernel", self.kernel_init or default, (fan_in, self.features))
        bias = self.param("bias", self.bias_init or default, (self.features,))
        x, kernel, bias = cast(self.dtype, x, kernel, bias)
        return x @ kernel + bias


class MLP(nn.Module):
    """Linear layers of widths `features`, ReLU between them, and after the last one if `final_relu`.

    `last_kernel_init` / `last_bias_init` override the initialisation of the last layer only."""
    features: Sequence[int]
    final_relu: bool = False
    first_kernel_init: Initializer | None = None
    last_kernel_init: Initializer | None = None
    last_bias_init: Initializer | None = None
    dtype: Dtype = None

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        n = len(self.features)
        for i, f in enumerate(self.features):
            last = i == n - 1
            k_init = self.last_kernel_init if last else None
            b_init = self.last_bias_init if last else None
            if i == 0 and self.first_kernel_init is not None:
                k_init = self.first_kernel_init
            x = TorchLinear(f, kernel_init=k_init, bias_init=b_init, dtype=self.dtype, name=f"layers_{i}")(x)
            if not last or self.final_relu:
                x = nn.relu(x)
        return x


def layer_norm(name: str | None = None, dtype: Dtype = None) -> nn.LayerNorm:
    """PyTorch's epsilon; statistics in float32 whatever `dtype` (the output's)."""
    return nn.LayerNorm(epsilon=LN_EPS, name=name, dtype=dtype)


def _split_heads(x: jax.Array, num_heads: int) -> jax.Array:
    """[..., T, D] -> [..., H, T, D/H]."""
    *lead, t, d = x.shape
    return jnp.swapaxes(x.reshape(*lead, t, num_heads, d // num_heads), -2, -3)


def _merge_heads(x: jax.Array) -> jax.Array:
    """[..., H, T, Dh] -> [..., T, H*Dh]."""
    x = jnp.swapaxes(x, -2, -3)
    return x.reshape(*x.shape[:-2], x.shape[-2] * x.shape[-1])


def attention_probs(q: jax.Array, k: jax.Array, key_mask: jax.Array, num_heads: int) -> jax.Array:
    """Softmax attention probabilities [..., H, Tq, Tk]; `key_mask` [..., Tk] is True for real keys.

    Padded keys get probability exactly 0 (exp underflows) as long as one key is real (the torso always
    is); a fully masked row gets uniform probabilities instead of NaNs. Logits and probabilities are float32
    whatever the dtype of q and k."""
    qh = _split_heads(q, num_heads)
    kh = _split_heads(k, num_heads)
    logits = jnp.einsum("...hqd,...hkd->...hqk", qh, kh, preferred_element_type=jnp.float32) / math.sqrt(qh.shape[-1])
    logits = jnp.where(key_mask[..., None, None, :], logits, jnp.finfo(logits.dtype).min)
    return jax.nn.softmax(logits, axis=-1)


def weighted_values(probs: jax.Array, v: jax.Array, num_heads: int) -> jax.Array:
    """The heads' probability-weighted values, merged: probs [..., H, T, T], v [..., T, D] -> [..., T, D]."""
    out = jnp.einsum("...hqk,...hkd->...hqd", probs.astype(v.dtype), _split_heads(v, num_heads))
    return _merge_heads(out)


#: how ordinary self-attention is computed (speed only, the same function): "einsum" (ours: heads split to [H, T, Dh],
#: float32 logits, `attention_probs`), "xla" / "cudnn" (`jax.nn.dot_product_attention` on [T, H, Dh] without head
#: transposes; cuDNN's fused kernel needs a GPU and bf16)
ATTENTION = ("einsum", "xla", "cudnn")


def dot_product_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_mask: jax.Array, num_heads: int,
                          implementation: str) -> jax.Array:
    """Self-attention through `jax.nn.dot_product_attention`: q, k, v [..., T, D], key_mask [..., T] -> [..., T, D]."""
    *lead, t, d = q.shape
    heads = lambda x: x.reshape(-1, t, num_heads, d // num_heads)
    # (batch, heads, queries, keys), the query axis full: cuDNN's kernel takes no mask broadcast over queries
    mask = jnp.broadcast_to(key_mask.reshape(-1, 1, 1, t), (math.prod(lead), 1, t, t))
    out = jax.nn.dot_product_attention(heads(q), heads(k), heads(v), mask=mask, implementation=implementation)
    return out.reshape(*lead, t, d)


class EncoderLayer(nn.Module):
    """Pre-norm encoder layer:  x += MHA(LN1(x)) ;  x += W2 ReLU(W1 LN2(x) + b1) + b2.

    `fixed=True` (ModuMorph): queries and keys are `norm_context(c_fa) W_{q,k}`, only the values come from
    `LN1(x)`. The probabilities then depend on the robot alone; `fixed_probs` computes them once per robot
    and `__call__` takes them (gathered per sample) instead of a key mask. `attention` (ordinary attention only):
    one of ATTENTION."""
    d_model: int
    num_heads: int
    ffn_dim: int
    fixed: bool = False
    dtype: Dtype = None
    attention: str = "einsum"

    def setup(self):
        d = self.d_model
        if d % self.num_heads:
            raise ValueError(f"d_model {d} is not divisible by num_heads {self.num_heads}")
        # xavier-uniform on PyTorch's packed (3D, D) in_proj_weight: bound sqrt(6 / (D + 3D)); the same
        # bound on our (D, 3D) layout.
        self.in_proj_kernel = self.param("in_proj_kernel", uniform(math.sqrt(6.0 / (4 * d))), (d, 3 * d))
        self.in_proj_bias = self.param("in_proj_bias", zeros, (3 * d,))
        self.out_proj = TorchLinear(d, bias_init=zeros, dtype=self.dtype)
        self.norm1 = layer_norm(dtype=self.dtype)
        self.norm2 = layer_norm(dtype=self.dtype)
        self.linear1 = TorchLinear(self.ffn_dim, dtype=self.dtype)
        self.linear2 = TorchLinear(d, dtype=self.dtype)
        if self.fixed:
            self.norm_context = layer_norm(dtype=self.dtype)

    def _proj(self, x: jax.Array, which: int) -> jax.Array:
        d = self.d_model
        x, w, b = cast(self.dtype, x, self.in_proj_kernel[:, which * d:(which + 1) * d],
                       self.in_proj_bias[which * d:(which + 1) * d])
        return x @ w + b

    def fixed_probs(self, c_fa: jax.Array, key_mask: jax.Array) -> jax.Array:
        """Fixed-attention probabilities [..., H, 12, 12] from the context encoding c_fa [..., 12, D]."""
        y = self.norm_context(c_fa)
        return attention_probs(self._proj(y, 0), self._proj(y, 1), key_mask, self.num_heads)

    def __call__(self, x: jax.Array, attn: jax.Array) -> jax.Array:
        """x [N, 12, D]; attn = key mask [N, 12] (ordinary) or probabilities [N, H, 12, 12] (fixed)."""
        y = self.norm1(x)
        if self.fixed:
            out = weighted_values(attn, self._proj(y, 2), self.num_heads)
        else:
            y, w, b = cast(self.dtype, y, self.in_proj_kernel, self.in_proj_bias)
            q, k, v = jnp.split(y @ w + b, 3, axis=-1)
            if self.attention == "einsum":
                out = weighted_values(attention_probs(q, k, attn, self.num_heads), v, self.num_heads)
            else:
                out = dot_product_attention(q, k, v, attn, self.num_heads, self.attention)
        x = x + self.out_proj(out)
        y = self.norm2(x)
        return x + self.linear2(nn.relu(self.linear1(y)))
