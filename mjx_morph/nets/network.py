"""One network of the zoo: the actor (2 outputs per limb) or the critic (1 output per limb).

Every architecture is one `PolicyNet` configured by a `NetConfig`; actor and critic are two separate
instances with separate parameters, as in MetaMorph and ModuMorph. The forward pass is split into phases so that the
`Model` (model.py) can run each phase on the right set of rows:

    robot_cache(context, node_mask)     once per ROBOT: hypernetwork outputs, fixed-attention probabilities,
                                        context-MLP outputs            -> arrays with a leading robot axis R
    pre(parts, cache)                   per sample, every timestep (burn-in included): the per-limb embedding
                                        and the recurrent cell's input projection
    recur(state, xg, node_mask)         one step of the shared per-limb cell (inside `lax.scan`)
    post(pre, h, parts, cache)          per sample, window steps only: transformer, height-map encoder, decoder

`parts` holds per-sample inputs with ONE flattened leading axis N (= B for acting, T*B for training):
`proprio` [N,12,52], `state` [N,12,17], `prev_action` [N,12,2], `node_mask` [N,12], `hfield` [N,1410] or None,
`robot` [N] (row into the robot cache).

Per-robot work and the gather.
- Fixed attention: queries and keys depend on the context only, so the attention PROBABILITIES of every layer
  are computed once per robot ([R, layers, heads, 12, 12]) and gathered per sample (1,440 floats per sample
  for 5 layers x 2 heads); per sample only the value projection, probs @ v, the output projection and the
  FFN remain.
- Hypernetwork layers: the generated matrices W[r, l] ([R, 12, in, out]) are computed once per robot. Each
  sample then needs x[n, l] @ W[robot[n], l]. We write this as an einsum over the gathered table
  (`gathered_matvec`). There is no cheaper exact equivalent with static shapes: rewriting it through the
  hypernetwork head (bilinear in x and the context code) costs the same 52 x 128 intermediate per limb-sample
  and 128x the FLOPs, and evaluating x against all R robots' matrices costs R x the FLOPs. The gathered
  intermediate (in x out floats per limb-sample, ~27 KB for the 54 x 128 embedding) is comparable to the
  transformer's own activations. Alternatives measured and rejected (multiply-and-sum, a
  clipped gather, a one-hot matmul gather) are in docs/benchmarks.md, and so is a sort-by-robot grouped matmul
  (`jax.lax.ragged_dot`): 30-75x slower with JAX 0.11.2 on an H100, its backward a dense masked product
  (`experiments.bench_hn_matmul` reruns it).
- hyperrmomo's hypernetwork input changes every step (context code + recurrent state), so its generated
  matrices are per sample by construction; they are produced by one matmul per layer and consumed at once.
"""
from __future__ import annotations

import dataclasses
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from ..layout import ACTS_PER_TOKEN, CTX_DIM, HFIELD_DIM, NUM_TOKENS, OBS_DIM, STATE_DIM
from .layers import MLP, EncoderLayer, TorchLinear, cast, uniform, zeros
from .precision import DEFAULT as DEFAULT_PRECISION
from .precision import compute_dtype
from .recurrent import CELLS, zero_state

EMBED_INPUT_DIMS = {
    "obs": OBS_DIM,                                   # MetaMorph / ModuMorph: the 52 features
    "obs_action": OBS_DIM + ACTS_PER_TOKEN,           # R-MoMo (design B): [52 features, previous action 2]
    "state_action": STATE_DIM + ACTS_PER_TOKEN,       # R-MeMo (design A): [17 state features, previous action 2]
}


@dataclasses.dataclass(frozen=True)
class NetConfig:
    """Structure and sizes of one network (see `zoo.py` for the values of each architecture)."""
    base: str                        # "meta": shared embedding + self-attention; "modu": hypernetwork + fixed attention
    cell: str | None = None          # None | "lstm" | "gru"
    cell_site: str = "base"          # "base": cell between embedding and transformer; "hyper": inside the hypernetwork
    embed_input: str = "obs"         # input of the per-limb embedding, a key of EMBED_INPUT_DIMS
    plus_mlp: bool = False           # *_plus: two extra per-limb Linear layers (D -> plus_hidden -> D) before the transformer
    context_mlp: bool = False        # R-MeMo paper-text option: MLP(context) added to the cell output
    scale_context: bool = False      # sqrt(D) multiplies the context MLP's output too (as it does the cell output)
    cell_residual: bool = False      # transformer input = embedding + cell output (default: cell output alone)
    scale_after_cell: bool = False   # apply sqrt(D) after the cell (default: to the embedding, before the cell)
    embed_scale: bool = True         # MetaMorph's EMBEDDING_SCALE: multiply the embedding by sqrt(D)
    d_model: int = 128
    num_layers: int = 5
    num_heads: int = 2
    ffn_dim: int = 1024
    plus_hidden: int = 256
    hfield: bool = False
    hfield_size: int = HFIELD_DIM
    hfield_dims: tuple[int, ...] = (64, 64)
    decoder_dims: tuple[int, ...] = ()
    precision: str = DEFAULT_PRECISION   # fp32 | tf32 | bf16 (precision.py)
    attention: str = "einsum"        # base "meta": how self-attention is computed (layers.ATTENTION; speed only)

    @property
    def dtype(self):
        """Compute dtype of the layers (parameters stay float32)."""
        return compute_dtype(self.precision)

    @property
    def recurrent(self) -> bool:
        return self.cell is not None

    @property
    def embed_in(self) -> int:
        return EMBED_INPUT_DIMS[self.embed_input]

    def decoder_layers(self, out_dim: int) -> list[int]:
        """[decoder input, hidden..., out]; the height-map code (hfield_dims[-1]) joins the decoder input."""
        d_in = self.d_model + (self.hfield_dims[-1] if self.hfield else 0)
        return [d_in, *self.decoder_dims, out_dim]


def take(table: jax.Array, idx: jax.Array) -> jax.Array:
    """Rows of a per-robot table for each sample."""
    return jnp.take(table, idx, axis=0)


def gathered_matvec(x: jax.Array, table: jax.Array, idx: jax.Array, dtype=jnp.float32) -> jax.Array:
    """x [N, L, I] times the per-robot matrices table [R, L, I, O] of each sample's robot -> [N, L, O] in `dtype`.
    The table stays float32 and is cast after the gather, so its gradient is scatter-added in float32 (a bfloat16
    scatter-add took a quarter of the bf16 update on an H100)."""
    return jnp.einsum("nli,nlio->nlo", x.astype(dtype), take(table, idx).astype(dtype))


class PolicyNet(nn.Module):
    cfg: NetConfig
    out_dim: int

    def setup(self):
        c = self.cfg
        d, dt = c.d_model, c.dtype
        modu = c.base == "modu"
        hyper_cell = c.recurrent and c.cell_site == "hyper"
        if c.base not in ("meta", "modu"):
            raise ValueError(f"unknown base {c.base!r}")
        dec = c.decoder_layers(self.out_dim)

        if c.base == "meta":
            # limb_embed: weight U(-0.1, 0.1) (EMBED_INIT), bias PyTorch default
            self.embed = TorchLinear(d, kernel_init=uniform(0.1), dtype=dt)
            # decoder: hidden layers PyTorch default, last layer weight U(-0.01, 0.01) (DECODER_INIT), bias 0
            self.decoder = MLP(dec[1:], last_kernel_init=uniform(0.01), last_bias_init=zeros, dtype=dt)
            if c.context_mlp:
                self.ctx_mlp = MLP([d, d], dtype=dt)
        else:
            # context encoders (context embedding size = d_model, CONTEXT_EMBED_SIZE), first layer U(-0.1, 0.1)
            self.fa_encoder = MLP([d, d, d], final_relu=True, first_kernel_init=uniform(0.1), dtype=dt)
            self.hn_encoder = MLP([d, d], final_relu=True, first_kernel_init=uniform(0.1), dtype=dt)
            # the heads make per-robot tables, kept float32 (cast per sample after the gather); hyperrmomo's make
            # per-sample layers, in the compute dtype
            head_dt = dt if hyper_cell else None
            # hypernetwork heads (arXiv 2210.11348 init): head weights 0, so at init the generated layers are
            # context-independent with MetaMorph's init ranges
            self.hn_embed_w = TorchLinear(c.embed_in * d, kernel_init=zeros, bias_init=uniform(0.1), dtype=head_dt)
            self.hn_embed_b = TorchLinear(d, kernel_init=zeros, bias_init=zeros, dtype=head_dt)
            self.hn_dec_w = [TorchLinear(a * b, kernel_init=zeros, bias_init=uniform(0.01), dtype=head_dt)
                             for a, b in zip(dec[:-1], dec[1:])]
            self.hn_dec_b = [TorchLinear(b, kernel_init=zeros, bias_init=zeros, dtype=head_dt) for b in dec[1:]]
        if c.recurrent:
            if hyper_cell:
                # hyperrmomo: the cell reads [17 state features, previous action 2] through its own embedding
                self.cell_embed = TorchLinear(d, kernel_init=uniform(0.1), dtype=dt)
            self.cell = CELLS[c.cell](d, d, dtype=dt)
        if c.plus_mlp:
            self.plus = MLP([c.plus_hidden, d], dtype=dt)
        self.layers = [EncoderLayer(d, c.num_heads, c.ffn_dim, fixed=modu, dtype=dt, attention=c.attention)
                       for _ in range(c.num_layers)]
        if c.hfield:
            # MLPObsEncoder: ReLU after every layer
            self.hfield_encoder = MLP(list(c.hfield_dims), final_relu=True, dtype=dt)

    # ------------------------------------------------------------------ per robot
    def robot_cache(self, context: jax.Array, node_mask: jax.Array) -> dict:
        """Everything that depends only on the robot: context [R, 12, 35], node_mask [R, 12] -> dict of [R, ...]."""
        c = self.cfg
        cache = {}
        if c.base == "meta":
            if c.context_mlp:
                ctx = self.ctx_mlp(context)
                cache["ctx"] = ctx * self._scale() if c.scale_context else ctx
            return cache
        r = context.shape[0]
        c_fa = self.fa_encoder(context)
        cache["probs"] = jnp.stack([layer.fixed_probs(c_fa, node_mask) for layer in self.layers], axis=1)
        c_hn = self.hn_encoder(context)
        if c.recurrent and c.cell_site == "hyper":
            cache["c_hn"] = c_hn
            return cache
        dec = c.decoder_layers(self.out_dim)
        cache["emb_w"] = self.hn_embed_w(c_hn).reshape(r, NUM_TOKENS, c.embed_in, c.d_model)
        cache["emb_b"] = self.hn_embed_b(c_hn)
        cache["dec_w"] = [hw(c_hn).reshape(r, NUM_TOKENS, a, b) for hw, a, b in zip(self.hn_dec_w, dec[:-1], dec[1:])]
        cache["dec_b"] = [hb(c_hn) for hb in self.hn_dec_b]
        return cache

    # ------------------------------------------------------------------ per sample
    def _embed_input(self, parts: dict) -> jax.Array:
        ei = self.cfg.embed_input
        if ei == "obs":
            return parts["proprio"]
        if ei == "obs_action":
            return jnp.concatenate([parts["proprio"], parts["prev_action"]], axis=-1)
        if ei == "state_action":
            return jnp.concatenate([parts["state"], parts["prev_action"]], axis=-1)
        raise ValueError(f"unknown embed_input {ei!r}")

    def _scale(self) -> float:
        return math.sqrt(self.cfg.d_model) if self.cfg.embed_scale else 1.0

    def pre(self, parts: dict, cache: dict) -> dict:
        """Per-limb embedding ('e') and, for recurrent nets, the cell's input projection ('xg')."""
        c = self.cfg
        if c.recurrent and c.cell_site == "hyper":
            u = self.cell_embed(jnp.concatenate([parts["state"], parts["prev_action"]], axis=-1))
            return {"xg": self.cell.input_proj(u)}
        x = self._embed_input(parts)
        if c.base == "meta":
            e = self.embed(x)
        else:
            e = (gathered_matvec(x, cache["emb_w"], parts["robot"], c.dtype)
                 + take(cache["emb_b"], parts["robot"]).astype(c.dtype))
        if not (c.recurrent and c.scale_after_cell):
            e = e * self._scale()
        out = {"e": e}
        if c.recurrent:
            out["xg"] = self.cell.input_proj(e)
        return out

    def recur(self, state: dict, xg: jax.Array, node_mask: jax.Array) -> tuple[dict, jax.Array]:
        """One cell step on [N, 12, ...]; state and output are zeroed on padded limbs."""
        state, h = self.cell.recur(state, xg)
        m = node_mask[..., None]
        state = jax.tree.map(lambda s: jnp.where(m, s, 0.0), state)
        return state, jnp.where(m, h, 0.0)

    def post(self, pre: dict, h: jax.Array | None, parts: dict, cache: dict) -> jax.Array:
        """Transformer, height-map encoder and decoder -> per-limb outputs [N, 12, out_dim]."""
        c = self.cfg
        idx = parts["robot"]
        hyper_cell = c.recurrent and c.cell_site == "hyper"
        dec = c.decoder_layers(self.out_dim)
        n = idx.shape[0]
        if hyper_cell:
            # the hypernetwork reads the context code plus the recurrent state: per-sample generated layers
            z = take(cache["c_hn"], idx) + h
            w = self.hn_embed_w(z).reshape(n, NUM_TOKENS, c.embed_in, c.d_model)
            x = jnp.einsum("nli,nlio->nlo", self._embed_input(parts).astype(w.dtype), w) + self.hn_embed_b(z)
            x = x * self._scale()
        else:
            x = pre["e"]
            if c.recurrent:
                x = x + h if c.cell_residual else h
                if c.scale_after_cell:
                    x = x * self._scale()
        if c.plus_mlp:
            x = self.plus(x)
        if c.context_mlp:
            x = x + take(cache["ctx"], idx)
        (x,) = cast(c.dtype, x)                                    # the transformer's residual stream

        if c.base == "modu":
            probs = take(cache["probs"], idx)                      # [N, layers, heads, 12, 12]
            for i, layer in enumerate(self.layers):
                x = layer(x, probs[:, i])
        else:
            for layer in self.layers:
                x = layer(x, parts["node_mask"])

        if c.hfield:
            hf = self.hfield_encoder(parts["hfield"])             # [N, 64], late fusion to every limb
            x = jnp.concatenate([x, jnp.broadcast_to(hf[:, None, :], (n, NUM_TOKENS, hf.shape[-1]))], axis=-1)

        if c.base == "meta":
            return self.decoder(x)
        last = len(dec) - 2
        for k, (a, b) in enumerate(zip(dec[:-1], dec[1:])):
            if hyper_cell:
                w = self.hn_dec_w[k](z).reshape(n, NUM_TOKENS, a, b)
                x = jnp.einsum("nli,nlio->nlo", x.astype(w.dtype), w) + self.hn_dec_b[k](z)
            else:
                x = gathered_matvec(x, cache["dec_w"][k], idx, c.dtype) + take(cache["dec_b"][k], idx).astype(c.dtype)
            if k < last:
                x = nn.relu(x)
        return x

    def __call__(self, context: jax.Array, node_mask: jax.Array, parts: dict) -> jax.Array:
        """One step from a zero state: touches every parameter (used by `init`)."""
        cache = self.robot_cache(context, node_mask)
        pre = self.pre(parts, cache)
        h = None
        if self.cfg.recurrent:
            n = parts["robot"].shape[0]
            state = zero_state(self.cfg.cell, (n, NUM_TOKENS), self.cfg.d_model)
            _, h = self.recur(state, pre["xg"], parts["node_mask"])
        return self.post(pre, h, parts, cache)
