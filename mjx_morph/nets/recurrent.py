"""Shared per-limb recurrent cells with PyTorch's parameterisation (two bias vectors).

One cell is shared by all 12 limb tokens of a network (and by all robots); its state has shape
[..., 12, H]. The cells are split in two so that the expensive part runs outside the time scan:

- `input_proj(x)`: the input-to-hidden projection for every timestep at once (one large matmul over T*B);
- `recur(state, xg)`: the hidden-to-hidden part, the only thing inside `lax.scan`.

LSTM (PyTorch `nn.LSTM`, gate order i, f, g, o):
    gates = x W_ih + b_ih + h W_hh + b_hh
    c' = sigmoid(f) * c + sigmoid(i) * tanh(g);   h' = sigmoid(o) * tanh(c')
`b_ih` and `b_hh` are added together, so one of them is redundant: it is kept only so that the parameter
count equals PyTorch's 4H(I + H + 2) (Flax's own LSTM cells have 4H fewer), which the paper's table
counts. Parameters: 132,096 for I = H = 128.

GRU (PyTorch `nn.GRU`, gate order r, z, n):
    r = sigmoid(x W_ir + b_ir + h W_hr + b_hr);  z = sigmoid(x W_iz + b_iz + h W_hz + b_hz)
    n = tanh(x W_in + b_in + r * (h W_hn + b_hn));  h' = (1 - z) * n + z * h
3H(I + H + 2) parameters (99,072 for I = H = 128). Here only the r and z parts of the two biases are
redundant; b_hn sits inside the reset gate and is not.

Initialisation as PyTorch: every weight and bias U(-1/sqrt(H), 1/sqrt(H)).

`dtype` (precision.py): the two matmuls run in it; the gate non-linearities and the state stay float32, so the
state carried over hundreds of steps is not rounded to bfloat16 at every step.
"""
from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from .layers import Dtype, cast, uniform


class _TorchCell(nn.Module):
    """PyTorch's parameters of a cell with `num_gates` gates: w_ih (I, G*H), w_hh (H, G*H), b_ih and b_hh (G*H,)."""
    in_features: int
    hidden: int
    dtype: Dtype = None

    num_gates = 0

    def setup(self):
        h, i, g = self.hidden, self.in_features, self.num_gates
        init = uniform(1.0 / math.sqrt(h))
        self.w_ih = self.param("w_ih", init, (i, g * h))
        self.w_hh = self.param("w_hh", init, (h, g * h))
        self.b_ih = self.param("b_ih", init, (g * h,))
        self.b_hh = self.param("b_hh", init, (g * h,))


class LSTMCell(_TorchCell):
    num_gates = 4

    def input_proj(self, x: jax.Array) -> jax.Array:
        x, w, b = cast(self.dtype, x, self.w_ih, self.b_ih + self.b_hh)
        return x @ w + b

    def recur(self, state: dict, xg: jax.Array) -> tuple[dict, jax.Array]:
        h, w = cast(self.dtype, state["h"], self.w_hh)
        gates = (xg + h @ w).astype(jnp.float32)
        i, f, g, o = jnp.split(gates, 4, axis=-1)
        c = jax.nn.sigmoid(f) * state["c"] + jax.nn.sigmoid(i) * jnp.tanh(g)
        h = jax.nn.sigmoid(o) * jnp.tanh(c)
        return {"h": h, "c": c}, h


class GRUCell(_TorchCell):
    num_gates = 3

    def input_proj(self, x: jax.Array) -> jax.Array:
        x, w, b = cast(self.dtype, x, self.w_ih, self.b_ih)
        return x @ w + b

    def recur(self, state: dict, xg: jax.Array) -> tuple[dict, jax.Array]:
        h, w, b = cast(self.dtype, state["h"], self.w_hh, self.b_hh)
        hg = (h @ w + b).astype(jnp.float32)
        xr, xz, xn = jnp.split(xg.astype(jnp.float32), 3, axis=-1)
        hr, hz, hn = jnp.split(hg, 3, axis=-1)
        r = jax.nn.sigmoid(xr + hr)
        z = jax.nn.sigmoid(xz + hz)
        n = jnp.tanh(xn + r * hn)
        h = (1.0 - z) * n + z * state["h"]
        return {"h": h}, h


CELLS = {"lstm": LSTMCell, "gru": GRUCell}


def zero_state(kind: str, shape: tuple[int, ...], hidden: int, dtype=jnp.float32) -> dict:
    """All-zero state of a cell for leading `shape` (e.g. (B, 12))."""
    z = jnp.zeros((*shape, hidden), dtype)
    return {"h": z, "c": z} if kind == "lstm" else {"h": z}
