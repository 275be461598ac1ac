"""The model zoo: which `NetConfig` each architecture name stands for, and `make_model`.

| arch            | per-limb path (each of actor and critic)                                                        |
|-----------------|-------------------------------------------------------------------------------------------------|
| metamorph       | Linear(52->D) * sqrt(D) -> 5 pre-norm self-attention layers -> decoder (MetaMorph*, §1)          |
| modumorph       | HN-generated Linear(52->D) * sqrt(D) -> 5 fixed-attention layers -> HN-generated decoder (§2)    |
| rmemo           | Linear([17 state, 2 prev action] -> D) * sqrt(D) -> LSTM(D) -> MetaMorph transformer, decoder    |
|                 | (design A, §3: this network never sees the 35 context features); `context_mlp=True` adds the     |
|                 | paper text's MLP(context) 35 -> D -> ReLU -> D to the LSTM output: +21,120 per network,           |
|                 | +42,240 in all, 3,610,499 instead of the paper's 3,568,259 (which therefore has no such MLP)       |
| rmomo           | HN-generated Linear([52 obs, 2 prev action] -> D) * sqrt(D) -> LSTM(D) -> ModuMorph (design B)   |
| grumomo         | rmomo with a GRU                                                                                |
| hyperrmomo      | ModuMorph whose hypernetwork reads (context code + LSTM state), the LSTM reading                |
|                 | Linear([17 state, 2 prev action] -> D); the base network has no cell                              |
| metamorph_plus  | metamorph + Linear(D->256) -> ReLU -> Linear(256->D) between embedding and transformer            |
| modumorph_plus  | modumorph + the same two layers at the same place                                                |

Design choices where the original papers and code leave a gap, all overridable by flags:
- The cell's output REPLACES the embedding as the transformer input (`cell_residual=False`); the spec's
  design B says the LSTM output "feeds" the transformer. Adding it to the embedding instead gave R-MoMo no gain
  (1 seed x 20 M steps on ft against 2 of the default; docs/results-log.md, "R-MoMo: the cell's output ...").
- sqrt(D) (EMBEDDING_SCALE) stays on the embedding, i.e. BEFORE the cell (`scale_after_cell=False`): the
  cell is inserted after the embedding step exactly as the feed-forward model computes it. This is the flag's
  default here; runs of rmomo, grumomo and rmemo get `scale_after_cell=True` from `RECOMMENDED` (measured, below:
  +45% training return for R-MoMo, +60% for R-MeMo with its context MLP, 2 seeds each over the first 20 M steps on
  ft), and runs of rmemo `context_mlp=True` and `scale_context=True` (measured, below; the flags' defaults here stay
  design A, the paper's count).
- R-MeMo's context MLP output is added to the cell output, as the paper's text says. The flag's default here adds it
  unscaled, after sqrt(D) (`scale_context=False`): at init the transformer input is then ten times smaller than
  MetaMorph's, and the context a third of it (tests/test_nets.py, test_rmemo_transformer_input_at_init_against_
  metamorph), and R-MeMo trained 39% below MetaMorph over the first 18 M steps on ft (2 seeds each, session 26).
  Runs of rmemo get `scale_context=True` from `RECOMMENDED` (sqrt(D) multiplies the context MLP's output too;
  measured, below); `embed_input="obs_action"` with `context_mlp=False` (the cell reads all 52 features, as
  R-MoMo's does) closed the gap as well, a little less (study ab_rmemo_context_path, docs/results-log.md).
- The previous action is clipped to [-1, 1] (the executed control), masked and zeroed at resets (model.py).
- The plus-variants put their two layers where the recurrent cell sits (per limb, between embedding and
  transformer, output replacing the embedding, ReLU between the layers only), so that "recurrent cell vs
  extra feed-forward depth at the same place" is the comparison. (+65,920 parameters per network.)
- hyperrmomo: z_l(t) = c^HN_l + h_l(t) feeds every hypernetwork head (embedding and decoder), so the
  generated layers change with the history. Adding (rather than concatenating) keeps the heads' sizes equal
  to ModuMorph's. At init the heads' weights are zero, so it starts exactly like ModuMorph and the LSTM has
  no influence (nor gradient) until the first update has moved the head weights (their gradient is
  proportional to z, which contains h). The LSTM input is the R-MeMo path (Linear(19 -> D), unscaled); the
  base embedding reads the 52 features and keeps the sqrt(D) scale.
- The transformer layers of one network start equal (`clone_layer_init`), as PyTorch's TransformerEncoder
  deep-copies one initialised layer; actor and critic are initialised independently.
- GRU keeps PyTorch's two bias vectors, 3H(I + H + 2) parameters.
- `attention=xla|cudnn` (metamorph, rmemo) computes the same self-attention through `jax.nn.dot_product_attention`,
  without our head transposes: a speed option, equal to the default `einsum` to float rounding (tests/test_nets.py).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Iterable, List, Mapping, Optional, Sequence

from . import precision as _precision
from .layers import ATTENTION
from .model import Model
from .network import EMBED_INPUT_DIMS, NetConfig

ARCHS: tuple[str, ...] = ("metamorph", "rmemo", "modumorph", "rmomo",
                          "grumomo", "hyperrmomo", "metamorph_plus", "modumorph_plus")

_STRUCTURE: dict[str, dict[str, Any]] = {
    "metamorph": dict(base="meta"),
    "rmemo": dict(base="meta", cell="lstm", embed_input="state_action"),
    "modumorph": dict(base="modu"),
    "rmomo": dict(base="modu", cell="lstm", embed_input="obs_action"),
    "grumomo": dict(base="modu", cell="gru", embed_input="obs_action"),
    "hyperrmomo": dict(base="modu", cell="lstm", cell_site="hyper"),
    "metamorph_plus": dict(base="meta", plus_mlp=True),
    "modumorph_plus": dict(base="modu", plus_mlp=True),
}

#: Measured choices where the spec leaves a gap, filled in by `experiments.run` (config composition) when the run does
#: not set the key, and then recorded in the run's config.yaml. `make_model` itself keeps the spec's first reading
#: (the flags' defaults above), so a saved `null` always means that reading.
#: rmomo / grumomo scale_after_cell=True: 2 seeds x 9.5 M steps on ft, 2.3x the training return of the sqrt(D)-before-
#: the-cell reading (docs/results-log.md, "R-MoMo: sqrt(D) before or after the cell"); grumomo follows rmomo so that
#: the LSTM/GRU ablation differs in the cell alone.
#: rmemo context_mlp=True: 2 seeds x 20 M steps on ft, training return 763 / 371 against 237 / 209 without the context
#: MLP, both seeds above both from 8 M steps on (docs/results-log.md, "R-MeMo: the context MLP, and sqrt(D) after the
#: cell"); design A's R-MeMo never sees the morphology. +42,240 parameters over the paper's table (3,610,499).
#: rmemo scale_context=True: 2 seeds x 18 M steps on ft, training return 1337 / 1532 against 1016 / 542 with the context
#: MLP's output unscaled, test70 1028 against 836, the variants (seed 1) 1801 against 943 (docs/results-log.md,
#: "R-MeMo's context path"); the paper's text (the context MLP added to the cell output) with both under sqrt(D).
RECOMMENDED: dict[str, dict[str, Any]] = {
    "rmomo": {"scale_after_cell": True},
    "grumomo": {"scale_after_cell": True},
    "rmemo": {"context_mlp": True, "scale_after_cell": True, "scale_context": True},
}
#: a recommended option that means something only where another option is on: not filled in where that one is off
#: (R-MeMo with `context_mlp=False`, design A, has no context MLP output to scale)
_NEEDS: dict[str, str] = {"scale_context": "context_mlp"}


def recommended(arch: str, options: Mapping[str, Any], named: Iterable[str] = ()) -> dict[str, Any]:
    """The measured options (`RECOMMENDED`) that a run of `arch` with model `options` (None: unset) gets: those it
    leaves unset and does not name in `named`, less any whose prerequisite (`_NEEDS`) ends up off."""
    named = set(named)
    fill = {k: v for k, v in RECOMMENDED.get(arch, {}).items() if options.get(k) is None and k not in named}
    final = {**options, **fill}
    return {k: v for k, v in fill.items() if k not in _NEEDS or final.get(_NEEDS[k])}

_SIZES = ("d_model", "num_layers", "num_heads", "ffn_dim", "plus_hidden", "hfield_size", "hfield_dims")
_MODEL_FLAGS = ("action_std", "clip_prev_action", "clone_layer_init", "scan_unroll")


@dataclasses.dataclass
class ModelOptions:
    """Overrides of an architecture's sizes and flags (`experiments.run model.<key>=...`); None keeps the
    architecture's own value (`NetConfig` / `Model` defaults, `_STRUCTURE`). Which keys apply to which architecture
    is checked by `make_model`."""
    d_model: Optional[int] = None
    num_layers: Optional[int] = None
    num_heads: Optional[int] = None
    ffn_dim: Optional[int] = None
    hidden: Optional[int] = None            # recurrent cell size (must equal d_model)
    plus_hidden: Optional[int] = None       # *_plus: width of the extra per-limb layers
    hfield_size: Optional[int] = None
    hfield_dims: Optional[List[int]] = None
    embed_input: Optional[str] = None       # obs | obs_action | state_action
    embed_scale: Optional[bool] = None
    context_mlp: Optional[bool] = None      # R-MeMo: the paper text's MLP(context) added to the cell output
    scale_context: Optional[bool] = None    # R-MeMo: sqrt(D) multiplies the context MLP's output too
    cell_residual: Optional[bool] = None    # transformer input = embedding + cell output
    scale_after_cell: Optional[bool] = None  # sqrt(D) after the cell instead of before it
    action_std: Optional[float] = None
    clip_prev_action: Optional[bool] = None
    clone_layer_init: Optional[bool] = None
    scan_unroll: Optional[int] = None       # recurrent cell: time steps per scan iteration (speed only, same result)
    attention: Optional[str] = None         # self-attention (metamorph, rmemo): einsum | xla | cudnn (speed only)

    def overrides(self) -> dict[str, Any]:
        """The keys that are set, as `make_model` keyword arguments."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


def _allowed(arch: str) -> set[str]:
    s = _STRUCTURE[arch]
    keys = set(_SIZES) | set(_MODEL_FLAGS) | {"embed_scale"}
    if s.get("cell"):
        keys.add("hidden")
        if s.get("cell_site", "base") == "base":
            keys |= {"cell_residual", "scale_after_cell", "embed_input"}
    if s["base"] == "meta":
        keys |= {"context_mlp", "scale_context", "attention"}
    if not s.get("cell"):
        keys.add("embed_input")
    return keys


def make_model(arch: str, *, hfield: bool, decoder_dims: Sequence[int] = (), precision: str = _precision.DEFAULT,
               **overrides: Any) -> Model:
    """Build an architecture of `ARCHS`.

    hfield: the task has the 1410-value height map (csr, obstacle); decoder_dims: the task's hidden decoder
    layers ([] for ft/incline, [64] csr, [64, 64] obstacle); precision: fp32 | tf32 | bf16 (precision.py).
    `overrides`: sizes (d_model, num_layers,
    num_heads, ffn_dim, hidden (= d_model), plus_hidden, hfield_dims, hfield_size) and flags (context_mlp,
    scale_context, cell_residual, scale_after_cell, embed_input, embed_scale, action_std, clip_prev_action,
    clone_layer_init, scan_unroll, attention), each only where it applies; anything else is an error."""
    if arch not in _STRUCTURE:
        raise ValueError(f"unknown architecture {arch!r}; known: {', '.join(ARCHS)}")
    allowed = _allowed(arch)
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise ValueError(f"{arch}: unknown or inapplicable option(s) {unknown}; allowed: {sorted(allowed)}")
    ov = dict(overrides)
    model_kw = {k: ov.pop(k) for k in _MODEL_FLAGS if k in ov}
    hidden = ov.pop("hidden", None)
    if hidden is not None and hidden != ov.get("d_model", NetConfig.d_model):
        raise ValueError(f"{arch}: the recurrent hidden size ({hidden}) must equal d_model "
                         f"({ov.get('d_model', NetConfig.d_model)}): the cell output is the transformer input")
    if "attention" in ov and ov["attention"] not in ATTENTION:
        raise ValueError(f"{arch}: attention={ov['attention']!r}; expected one of {', '.join(ATTENTION)}")
    if "embed_input" in ov and ov["embed_input"] not in EMBED_INPUT_DIMS:
        raise ValueError(f"{arch}: embed_input must be one of {sorted(EMBED_INPUT_DIMS)}")
    if ov.get("scale_context") and not ov.get("context_mlp"):
        raise ValueError(f"{arch}: scale_context=True scales the context MLP's output, so it needs context_mlp=True")
    if "hfield_dims" in ov:
        ov["hfield_dims"] = tuple(int(x) for x in ov["hfield_dims"])
    net = NetConfig(**{**_STRUCTURE[arch], **ov}, hfield=bool(hfield), decoder_dims=tuple(int(x) for x in decoder_dims),
                    precision=_precision.check(precision))
    return Model(arch, net, **model_kw)
