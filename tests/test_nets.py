"""The model zoo (mjx_morph.nets): parameter counts, masks, acting == training, resets, burn-in, caching,
the flags scale_after_cell, cell_residual and context_mlp (acting == training for each value, and what each
does), an independent NumPy reference forward for MetaMorph and ModuMorph, the cells, the distribution and the
parameter-count CLI.

Behavioural tests use tiny networks (d_model 16, 2 layers) and one set of shapes (R = B = 4 robots/envs,
T = 6 steps) so every jitted function compiles once per architecture; full-size networks are only traced
(`jax.eval_shape`) for counting."""
from __future__ import annotations

import functools
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_morph.layout import NUM_TOKENS, STATE_FEATURES, Obs, Robots
from mjx_morph.nets import ARCHS, NetConfig, distribution, make_model
from mjx_morph.nets.network import take
from mjx_morph.nets.recurrent import GRUCell, LSTMCell
from mjx_morph.run import FAST_COMPILE

ROOT = Path(__file__).resolve().parents[1]
TINY = dict(d_model=16, num_layers=2, num_heads=2, ffn_dim=32, plus_hidden=24, hfield_dims=(8, 8))
R = B = 4
T = 6
RECURRENT = ("rmemo", "rmomo", "grumomo", "hyperrmomo")


# ---------------------------------------------------------------------------------------------- counts
FT_COUNTS = {
    # the paper's table
    "metamorph": 3_312_515,
    "rmemo": 3_568_259,
    "modumorph": 5_218_819,    # paper 5,232,774 incl. 13,955 unused parameters
    "rmomo": 5_549_059,        # paper 5,563,526 incl. 14,467 unused parameters
    # ablations (ours): rmomo - 2 * (LSTM 132,096 - GRU 99,072)
    "grumomo": 5_483_011,
    # modumorph + 2 * (Linear(19->128) 2,560 + LSTM 132,096)
    "hyperrmomo": 5_488_131,
    # + 2 * (Linear(128->256) 33,024 + Linear(256->128) 32,896)
    "metamorph_plus": 3_444_355,
    "modumorph_plus": 5_350_659,
}


def count(arch, hfield=False, decoder_dims=(), **kw):
    return make_model(arch, hfield=hfield, decoder_dims=list(decoder_dims), **kw).num_params()


@pytest.mark.parametrize("arch", ARCHS)
def test_param_counts_flat_terrain(arch):
    assert count(arch) == FT_COUNTS[arch]


def test_param_counts_height_map_tasks():
    # the original code's counts (unused modules counted) minus the unused modules for ModuMorph
    assert count("metamorph", True, [64]) == 3_525_955
    assert count("metamorph", True, [64, 64]) == 3_534_275
    unused_csr = 2 * (52 * 128 + 128) + (192 * 64 + 64 + 64 * 2 + 2) + (192 * 64 + 64 + 64 + 1)
    assert count("modumorph", True, [64]) == 8_608_262 - unused_csr
    unused_obs = unused_csr + 2 * (64 * 64 + 64)
    assert count("modumorph", True, [64, 64]) == 9_689_862 - unused_obs


def test_param_count_rmemo_context_mlp():
    # paper-text option: MLP 35 -> 128 -> 128 per network, +2 * 21,120 (3,610,499)
    assert count("rmemo", context_mlp=True) == 3_610_499


# ---------------------------------------------------------------------------------------------- data
def make_robots(seed: int, n: int = R) -> Robots:
    rng = np.random.default_rng(seed)
    limbs = rng.integers(2, NUM_TOKENS, n)
    limbs[0] = NUM_TOKENS - 1
    node = np.arange(NUM_TOKENS)[None] < limbs[:, None]
    act = np.repeat(node, 2, axis=1) & (rng.random((n, 2 * NUM_TOKENS)) < 0.75)
    act[:, :2] = False
    ctx = rng.uniform(-1, 1, (n, NUM_TOKENS, 35)).astype(np.float32) * node[..., None]
    return Robots(jnp.asarray(ctx), jnp.asarray(node), jnp.asarray(act))


def make_obs(seed: int, shape, robot=None) -> Obs:
    k = jax.random.split(jax.random.key(seed), 4)
    if robot is None:
        robot = jax.random.randint(k[2], shape, 0, R)
    return Obs(jax.random.normal(k[0], (*shape, NUM_TOKENS, 52)),
               1.5 * jax.random.normal(k[1], (*shape, 2 * NUM_TOKENS)),
               jnp.asarray(robot, jnp.int32),
               jax.random.normal(k[3], (*shape, 1410)))


def at(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def random_params(model, robots, seed=1):
    """Random parameters of the right shapes, drawn with NumPy (no per-shape XLA compiles, unlike `init`).

    Not the PyTorch initialisation (test_initialisation checks that): every leaf is random, so ModuMorph's
    generated layers depend on the context and hyperrmomo's on its recurrent state (at init the hypernetwork
    heads' weights are 0 and neither would)."""
    shapes = jax.eval_shape(model.init, jax.random.key(0), robots, make_obs(0, (B,)))
    rng = np.random.default_rng(seed)

    def fill(path, x):
        name = getattr(path[-1], "key", "")
        v = rng.normal(size=x.shape) * (1.0 / np.sqrt(x.shape[0]) if len(x.shape) == 2 else 0.1)
        return jnp.asarray(v + (1.0 if name == "scale" else 0.0), jnp.float32)
    return jax.tree_util.tree_map_with_path(fill, shapes)


def fast_jit(f, **kw):
    """jax.jit with XLA's CPU backend optimisations off: these tiny programs compile ~2x faster and run in
    milliseconds anyway."""
    return jax.jit(f, compiler_options=FAST_COMPILE, **kw)


@functools.lru_cache(maxsize=None)
def setup(arch: str, hfield: bool = True, flags: tuple[tuple[str, object], ...] = ()):
    """Tiny model (with height map and a hidden decoder layer when hfield; `flags`: extra `make_model` options as
    (key, value) pairs), params, jitted step/sequence."""
    model = make_model(arch, hfield=hfield, decoder_dims=[8] if hfield else [], **{**TINY, **dict(flags)})
    robots = make_robots(0)
    params = random_params(model, robots)
    step = fast_jit(model.step)
    seq = fast_jit(model.sequence, static_argnames="burn_in")
    return model, robots, params, step, seq


def run_steps(step, params, robots, obs_seq, carry, resets):
    mus, vals = [], []
    for t in range(resets.shape[0]):
        mu, v, carry = step(params, robots, at(obs_seq, t), carry, resets[t])
        mus.append(mu)
        vals.append(v)
    return jnp.stack(mus), jnp.stack(vals), carry


def assert_close(a, b, tol=1e-5):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=tol, atol=tol)


def assert_tree_close(a, b, tol=1e-5):
    jax.tree.map(lambda x, y: assert_close(x, y, tol), a, b)


# ---------------------------------------------------------------------------------------------- behaviour
@pytest.mark.parametrize("arch", ARCHS)
def test_shapes_and_masks(arch):
    model, robots, params, step, _ = setup(arch)
    obs = make_obs(1, (B,))
    carry = model.initial_carry(B)
    mu, v, carry = step(params, robots, obs, carry, jnp.zeros(B, bool))
    assert mu.shape == (B, 24) and v.shape == (B,)
    act = robots.act_mask[obs.robot]
    assert np.all(np.asarray(mu)[~np.asarray(act)] == 0.0)
    assert np.all(np.isfinite(np.asarray(mu))) and np.all(np.isfinite(np.asarray(v)))
    if model.recurrent:
        node = np.asarray(robots.node_mask[obs.robot])
        for s in jax.tree.leaves(carry):
            assert s.shape == (B, NUM_TOKENS, 16)
            assert np.all(np.asarray(s)[~node] == 0.0)
            assert np.any(np.asarray(s)[node] != 0.0)
    else:
        assert carry == {} and model.initial_carry(B) == {}


@pytest.mark.parametrize("arch", ARCHS)
def test_padded_slots_do_not_matter(arch):
    """Real-limb outputs and real-limb states are unchanged when padded limbs / masked action entries,
    padded context rows and padded carry rows hold other values."""
    model, robots, params, step, _ = setup(arch)
    obs_seq = make_obs(2, (3, B))
    resets = jnp.zeros((3, B), bool)
    node = robots.node_mask[obs_seq.robot]                       # [3, B, 12]
    act = robots.act_mask[obs_seq.robot]
    junk = make_obs(3, (3, B))
    obs2 = obs_seq._replace(
        proprio=jnp.where(node[..., None], obs_seq.proprio, 7.0 * junk.proprio),
        prev_action=jnp.where(act, obs_seq.prev_action, 5.0 * junk.prev_action))
    robots2 = robots._replace(context=jnp.where(robots.node_mask[..., None], robots.context, 3.0))
    carry2 = model.initial_carry(B)
    if model.recurrent:
        pad = ~robots.node_mask[obs_seq.robot[0]][..., None]
        carry2 = jax.tree.map(lambda s: jnp.where(pad, 9.0, s), carry2)
    mu1, v1, c1 = run_steps(step, params, robots, obs_seq, model.initial_carry(B), resets)
    mu2, v2, c2 = run_steps(step, params, robots2, obs2, carry2, resets)
    assert_close(mu1, mu2)
    assert_close(v1, v2)
    assert_tree_close(c1, c2)
    # and a real entry does matter
    mu3, _, _ = run_steps(step, params, robots, obs_seq._replace(proprio=obs_seq.proprio.at[..., 0, :].add(1.0)),
                          model.initial_carry(B), resets)
    assert not np.allclose(np.asarray(mu1), np.asarray(mu3))


def random_resets(seed):
    rng = np.random.default_rng(seed)
    r = rng.random((T, B)) < 0.25
    r[0] = [True, False, False, True]
    return jnp.asarray(r)


def random_carry(model, seed):
    if not model.recurrent:
        return {}
    leaves, tree = jax.tree.flatten(model.initial_carry(B))
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    return jax.tree.unflatten(tree, [0.5 * jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)])


@pytest.mark.parametrize("arch", ARCHS)
def test_sequence_equals_steps(arch):
    model, robots, params, step, seq = setup(arch)
    obs_seq = make_obs(4, (T, B))
    resets = random_resets(4)
    carry0 = random_carry(model, 4)
    mu1, v1, c1 = run_steps(step, params, robots, obs_seq, carry0, resets)
    mu2, v2, c2 = seq(params, robots, obs_seq, carry0, resets, burn_in=0)
    assert mu2.shape == (T, B, 24) and v2.shape == (T, B)
    assert_close(mu1, mu2)
    assert_close(v1, v2)
    assert_tree_close(c1, c2)


@pytest.mark.parametrize("arch", ["rmomo", "metamorph"])
def test_batch_major_rows_give_the_same_sequence(arch):
    """batch_major (what the trainer uses where the batch is sharded over devices) changes only the order in which
    the per-sample networks see the window's rows: outputs, final carry and the burn-in's carry are the same."""
    model, robots, params, _, seq = setup(arch)
    obs_seq = make_obs(5, (T, B))
    resets = random_resets(5)
    carry0 = random_carry(model, 5)
    mu1, v1, c1 = seq(params, robots, obs_seq, carry0, resets, burn_in=2)
    run = fast_jit(functools.partial(model.sequence, burn_in=2, batch_major=True))
    mu2, v2, c2 = run(params, robots, obs_seq, carry0, resets)
    assert mu2.shape == mu1.shape == (T - 2, B, 24)
    assert_close(mu1, mu2)
    assert_close(v1, v2)
    assert_tree_close(c1, c2)
    adv = lambda bm: model.advance(params, robots, obs_seq, carry0, resets, batch_major=bm)
    assert_tree_close(adv(False), adv(True))


@pytest.mark.parametrize("arch", RECURRENT)
def test_done_in_the_middle_equals_two_sequences(arch):
    """A done flag at step k of one sequence == a sequence of k steps followed by a fresh sequence (zero
    state) that starts at step k. All calls use the same sequence length so nothing is recompiled: a
    sequence's first k outputs do not depend on its later inputs."""
    model, robots, params, _, seq = setup(arch)
    k = T // 2
    obs_seq = make_obs(5, (T, B))
    obs_seq = obs_seq._replace(prev_action=obs_seq.prev_action.at[k].set(0.0))   # as the env writes it
    resets = jnp.zeros((T, B), bool).at[k].set(True)
    no_resets = jnp.zeros((T, B), bool)
    carry0 = random_carry(model, 5)
    mu, v, c = seq(params, robots, obs_seq, carry0, resets, burn_in=0)
    mu_a, v_a, _ = seq(params, robots, obs_seq, carry0, no_resets, burn_in=0)           # first k steps
    rolled = jax.tree.map(lambda x: jnp.roll(x, -k, axis=0), obs_seq)                   # steps k, k+1, ...
    mu_b, v_b, _ = seq(params, robots, rolled, model.initial_carry(B), no_resets, burn_in=0)
    assert_close(mu[:k], mu_a[:k])
    assert_close(v[:k], v_a[:k])
    assert_close(mu[k:], mu_b[:T - k])
    assert_close(v[k:], v_b[:T - k])
    # the reset wipes any carry, and the previous action, at the start of the second episode
    junk = rolled._replace(prev_action=rolled.prev_action.at[0].set(3.0))
    mu_c, _, _ = seq(params, robots, junk, random_carry(model, 6), no_resets.at[0].set(True), burn_in=0)
    assert_close(mu[k:], mu_c[:T - k])
    # without the reset the second half differs
    assert not np.allclose(np.asarray(mu_a[k:]), np.asarray(mu[k:]))


@pytest.mark.parametrize("arch", RECURRENT + ("metamorph",))
def test_burn_in(arch):
    """burn_in steps only advance the cell: the outputs are the last T - burn_in of the full sequence, and no
    gradient reaches the burn-in inputs or the stored start state."""
    model, robots, params, _, seq = setup(arch)
    obs_seq = make_obs(7, (T, B))
    resets = random_resets(7).at[1:3].set(False)
    carry0 = random_carry(model, 7)
    burn = 2
    mu, v, c = seq(params, robots, obs_seq, carry0, resets, burn_in=0)

    def loss(proprio, carry):
        m, val, fin = model.sequence(params, robots, obs_seq._replace(proprio=proprio), carry, resets, burn_in=burn)
        return jnp.sum(m ** 2) + jnp.sum(val ** 2), (m, val, fin)
    (_, (mu_b, v_b, c_b)), (g_obs, g_carry) = fast_jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))(
        obs_seq.proprio, carry0)
    assert mu_b.shape == (T - burn, B, 24)
    assert_close(mu[burn:], mu_b)
    assert_close(v[burn:], v_b)
    assert_tree_close(c, c_b)
    assert np.all(np.asarray(g_obs[:burn]) == 0.0)
    assert np.any(np.asarray(g_obs[burn:]) != 0.0)
    assert all(np.all(np.asarray(g) == 0.0) for g in jax.tree.leaves(g_carry))


@pytest.mark.parametrize("arch", ARCHS)
def test_per_robot_cache_equals_per_sample(arch):
    """Robots shared by several samples (cache over R robots, gathered) == per-sample robots (R = B)."""
    model, robots, params, step, seq = setup(arch)
    robot_idx = jnp.array([[0, 2, 0, 3], [1, 2, 2, 0]] * (T // 2), jnp.int32)          # [T, B]
    obs_seq = make_obs(8, (T, B), robot=robot_idx)
    resets = random_resets(8)
    carry0 = random_carry(model, 8)
    mu1, v1, c1 = seq(params, robots, obs_seq, carry0, resets, burn_in=0)
    mu_s, v_s = [], []
    carry = carry0
    for t in range(T):
        per_sample = jax.tree.map(lambda x: x[robot_idx[t]], robots)                     # R = B
        o = at(obs_seq, t)._replace(robot=jnp.arange(B, dtype=jnp.int32))
        mu, v, carry = step(params, per_sample, o, carry, resets[t])
        mu_s.append(mu)
        v_s.append(v)
    assert_close(mu1, jnp.stack(mu_s))
    assert_close(v1, jnp.stack(v_s))
    assert_tree_close(c1, carry)
    if arch == "rmomo":
        # a precomputed cache (once per rollout) gives the same as computing it inside the call
        cache = fast_jit(model.robot_cache)(params, robots)
        mu2, _, _ = seq(params, robots, obs_seq, carry0, resets, burn_in=0, cache=cache)
        assert_close(mu1, mu2)


# ---------------------------------------------------------------------------------------------- model flags
FLAGS = ("scale_after_cell", "cell_residual", "context_mlp")
FLAG_CASES = [
    ("rmomo", {"scale_after_cell": False, "cell_residual": False}),
    ("rmomo", {"scale_after_cell": True}),
    ("rmomo", {"cell_residual": True}),
    ("rmomo", {"scale_after_cell": True, "cell_residual": True}),
    ("grumomo", {"scale_after_cell": True}),
    ("grumomo", {"cell_residual": True}),
    ("rmemo", {"scale_after_cell": False, "cell_residual": False, "context_mlp": False}),
    ("rmemo", {"scale_after_cell": True}),
    ("rmemo", {"cell_residual": True}),
    ("rmemo", {"context_mlp": True}),
    ("rmemo", {"context_mlp": True, "cell_residual": True, "scale_after_cell": True}),
    ("metamorph", {"context_mlp": True}),
]


def flag_setup(arch: str, flags: dict):
    """`setup` with the flags that differ from their defaults (so the default values share `setup(arch)`)."""
    non_default = tuple(sorted((k, v) for k, v in flags.items() if v != getattr(NetConfig, k)))
    return setup(arch, flags=non_default)


def silence_cells(params):
    """Parameters whose LSTMs output exactly 0: output-gate bias -1e4, so sigmoid(o) underflows to 0."""
    def silence(cell):
        h = cell["b_ih"].shape[0] // 4
        return {**cell, "b_ih": cell["b_ih"].at[3 * h:].set(-1e4)}
    return {name: {**p, "cell": silence(p["cell"])} for name, p in params.items()}


@pytest.mark.parametrize("arch,flags", FLAG_CASES,
                         ids=[a + "-" + "-".join(f"{k}={v}" for k, v in f.items()) for a, f in FLAG_CASES])
def test_flags_sequence_with_burn_in_equals_steps(arch, flags):
    """For every value of the NetConfig flags scale_after_cell, cell_residual and context_mlp: `sequence` with a
    burn-in (resets inside the burn-in and the window) gives the outputs of the last T - burn_in of T calls of
    `step` and the same final state; and a flag set away from its default changes the outputs."""
    model, robots, params, step, seq = flag_setup(arch, flags)
    assert {k: getattr(model.net, k) for k in flags} == flags
    burn = 2
    obs_seq = make_obs(12, (T, B))
    resets = random_resets(12).at[1].set([False, True, False, False])
    carry0 = random_carry(model, 12)
    mu1, v1, c1 = run_steps(step, params, robots, obs_seq, carry0, resets)
    mu2, v2, c2 = seq(params, robots, obs_seq, carry0, resets, burn_in=burn)
    assert mu2.shape == (T - burn, B, 24)
    assert_close(mu1[burn:], mu2)
    assert_close(v1[burn:], v2)
    assert_tree_close(c1, c2)
    if any(flags.values()):
        _, _, base_params, base_step, _ = setup(arch)
        if jax.tree.structure(base_params) == jax.tree.structure(params):      # context_mlp adds parameters
            mu0, _, _ = run_steps(base_step, params, robots, obs_seq, carry0, resets)
            assert not np.allclose(np.asarray(mu0), np.asarray(mu1), atol=1e-3)


@pytest.mark.parametrize("arch", ["rmomo", "rmemo", "grumomo"])
def test_scale_after_cell_keeps_the_cell_unsaturated_at_init(arch):
    """At full width (D = 128) and the PyTorch initialisation, on normalised inputs (proprio N(0, 1), previous
    action in [-1, 1]): with sqrt(D) on the embedding before the cell (scale_after_cell=False, the default) a large
    fraction of the cell's gate pre-activations at the first step have |x| > 2 (measured: 46% rmomo and grumomo,
    27% rmemo); with scale_after_cell=True none do (measured max |x| well below 2)."""
    fractions = {}
    for flag in (False, True):
        model = make_model(arch, hfield=False, decoder_dims=[], d_model=128, num_layers=1, ffn_dim=32,
                           scale_after_cell=flag)
        robots = make_robots(0)
        obs = make_obs(13, (32,))._replace(hfield=None)
        obs = obs._replace(prev_action=jnp.clip(obs.prev_action, -1.0, 1.0))
        params = model.init(jax.random.key(13), robots, obs)
        cache = model.robot_cache(params, robots)
        parts = model._parts(robots, obs, None)
        node = np.asarray(parts["node_mask"])
        for name, net in model.nets.items():
            # from a zero state the gate pre-activations are the input projection alone
            xg = np.asarray(net.apply({"params": params[name]}, parts, cache[name], method="pre")["xg"])[node]
            fractions[flag, name] = float(np.mean(np.abs(xg) > 2.0))
    for name in ("actor", "critic"):
        assert fractions[False, name] > 0.2, fractions
        assert fractions[True, name] < 0.005, fractions


def test_scale_after_cell_moves_sqrt_d_behind_the_cell():
    """scale_after_cell=True with input weights W equals scale_after_cell=False with W / sqrt(D), except that the
    cell's output is multiplied by sqrt(D): with no transformer layers and zero decoder biases (outputs linear in
    the transformer input) the outputs are sqrt(D) times larger and the states are equal."""
    kw = dict(hfield=False, decoder_dims=[], d_model=16, num_layers=0)
    after = make_model("rmemo", scale_after_cell=True, **kw)
    before = make_model("rmemo", scale_after_cell=False, **kw)
    robots = make_robots(0)
    params = random_params(after, robots)
    params = {name: {**p, "decoder": {"layers_0": {**p["decoder"]["layers_0"],
                                                    "bias": jnp.zeros_like(p["decoder"]["layers_0"]["bias"])}}}
              for name, p in params.items()}
    scaled = {name: {**p, "cell": {**p["cell"], "w_ih": p["cell"]["w_ih"] / 4.0}} for name, p in params.items()}
    obs = make_obs(14, (B,))._replace(hfield=None)
    carry = random_carry(after, 14)
    resets = jnp.zeros(B, bool)
    mu_a, v_a, c_a = after.step(params, robots, obs, carry, resets)
    mu_b, v_b, c_b = before.step(scaled, robots, obs, carry, resets)
    assert_tree_close(c_a, c_b)
    assert_close(mu_a, 4.0 * mu_b)                                        # sqrt(16)
    assert_close(v_a, 4.0 * v_b)
    assert np.abs(np.asarray(mu_b)).max() > 1e-2


@pytest.mark.parametrize("scale_after_cell", [False, True])
def test_cell_residual_adds_the_embedding(scale_after_cell):
    """With cells that output 0: cell_residual=True gives exactly the feed-forward ModuMorph with R-MoMo's
    embedding input (the transformer input is the embedding), cell_residual=False outputs that do not depend on
    the observation at all (the transformer input is the cell output alone)."""
    flags = {"scale_after_cell": scale_after_cell}
    model, robots, params, step, _ = flag_setup("rmomo", {**flags, "cell_residual": True})
    ff, _, ff_params, ff_step, _ = setup("modumorph", flags=(("embed_input", "obs_action"),))
    _, _, _, step_alone, _ = flag_setup("rmomo", {**flags, "cell_residual": False})
    silent = silence_cells(params)
    shared = {name: {k: v for k, v in p.items() if k != "cell"} for name, p in silent.items()}
    assert jax.tree.structure(shared) == jax.tree.structure(ff_params)
    obs, other = make_obs(15, (B,)), make_obs(16, (B,))
    other = other._replace(robot=obs.robot, hfield=obs.hfield)            # only the per-limb inputs differ
    carry = random_carry(model, 15)
    resets = jnp.zeros(B, bool)
    mu, v, c = step(silent, robots, obs, carry, resets)
    mu_ff, v_ff, _ = ff_step(shared, robots, obs, {}, resets)
    assert all(np.all(np.asarray(x) == 0.0) for x in jax.tree.leaves({n: s["h"] for n, s in c.items()}))
    assert_close(mu, mu_ff)
    assert_close(v, v_ff)
    mu1, v1, _ = step_alone(silent, robots, obs, carry, resets)
    mu2, v2, _ = step_alone(silent, robots, other, carry, resets)
    assert_close(mu1, mu2)
    assert_close(v1, v2)
    assert not np.allclose(np.asarray(mu1), np.asarray(mu), atol=1e-3)


@pytest.mark.parametrize("arch", ["rmemo", "metamorph"])
def test_context_mlp_gives_the_context(arch):
    """rmemo (design A) and metamorph read no context features: their outputs do not change when only the robots'
    context changes. With context_mlp=True an MLP of the context is added to the transformer input, so they do;
    for rmemo with cells that output 0, the outputs then depend on the context and not on the observation."""
    robots = make_robots(0)
    other_robots = robots._replace(context=make_robots(1).context * robots.node_mask[..., None])
    obs = make_obs(17, (B,))
    other = make_obs(18, (B,))._replace(robot=obs.robot, hfield=obs.hfield)
    model, _, params, step, _ = setup(arch)
    carry = random_carry(model, 17)
    resets = jnp.zeros(B, bool)
    mu1, v1, _ = step(params, robots, obs, carry, resets)
    mu2, v2, _ = step(params, other_robots, obs, carry, resets)
    assert_close(mu1, mu2)
    assert_close(v1, v2)
    model, _, params, step, _ = flag_setup(arch, {"context_mlp": True})
    mu1, v1, _ = step(params, robots, obs, carry, resets)
    mu2, v2, _ = step(params, other_robots, obs, carry, resets)
    assert not np.allclose(np.asarray(mu1), np.asarray(mu2), atol=1e-3)
    assert not np.allclose(np.asarray(v1), np.asarray(v2), atol=1e-3)
    if model.recurrent:
        silent = silence_cells(params)
        mu_a, _, _ = step(silent, robots, obs, carry, resets)
        mu_b, _, _ = step(silent, robots, other, carry, resets)
        mu_c, _, _ = step(silent, other_robots, obs, carry, resets)
        assert_close(mu_a, mu_b)
        assert not np.allclose(np.asarray(mu_a), np.asarray(mu_c), atol=1e-3)


def test_scale_context_multiplies_the_context_mlp_output_by_sqrt_d():
    """scale_context=True with context-MLP output weights W equals scale_context=False with sqrt(D) W (the last
    layer's kernel and bias; D = 16 here, so 4): the same outputs and states. And it needs context_mlp."""
    flags = {"context_mlp": True, "scale_after_cell": True}
    model, robots, params, step, _ = flag_setup("rmemo", flags)
    _, _, _, step_scaled, _ = flag_setup("rmemo", {**flags, "scale_context": True})

    def times4(p):
        last = p["ctx_mlp"]["layers_1"]
        return {**p, "ctx_mlp": {**p["ctx_mlp"], "layers_1": jax.tree.map(lambda x: 4.0 * x, last)}}
    obs = make_obs(19, (B,))
    carry = random_carry(model, 19)
    resets = jnp.zeros(B, bool)
    mu_s, v_s, c_s = step_scaled(params, robots, obs, carry, resets)
    mu_w, v_w, c_w = step({n: times4(p) for n, p in params.items()}, robots, obs, carry, resets)
    mu, _, _ = step(params, robots, obs, carry, resets)
    assert_close(mu_s, mu_w)
    assert_close(v_s, v_w)
    assert_tree_close(c_s, c_w)
    assert not np.allclose(np.asarray(mu_s), np.asarray(mu), atol=1e-3)
    with pytest.raises(ValueError, match="scale_context=True .* needs context_mlp=True"):
        make_model("rmemo", hfield=False, scale_context=True)


def test_rmemo_transformer_input_at_init_against_metamorph():
    """At full width (D = 128) and the PyTorch initialisation, on normalised inputs (all 52 proprio features
    N(0, 1), context in [-1, 1], as the learner's normaliser and ModuMorph's bounds give them), the transformer's
    input at the first step: MetaMorph's (sqrt(D) times the embedding of the 52 features, 35 of them the context)
    has rms 4.8; R-MeMo's with its defaults (sqrt(D) times the cell output, plus the context MLP's output) is ten
    times smaller, and the context's part of it is a third of the cell's (rms 0.14 against 0.48). scale_context=True
    puts the context MLP's output under sqrt(D) (rms 1.6): the context then outweighs the cell output, as it does
    in MetaMorph's embedding."""
    robots = make_robots(0)
    obs = make_obs(20, (64,))._replace(hfield=None)
    obs = obs._replace(prev_action=jnp.clip(obs.prev_action, -1.0, 1.0))
    kw = dict(hfield=False, decoder_dims=[], d_model=128, num_layers=1, ffn_dim=32)

    def rms(x, mask):
        return float(np.sqrt(np.mean(np.square(np.asarray(x)[np.asarray(mask)]))))

    meta = make_model("metamorph", **kw)
    params = meta.init(jax.random.key(20), robots, obs)
    parts = meta._parts(robots, obs, None)
    node = parts["node_mask"]
    e = meta.nets["actor"].apply({"params": params["actor"]}, parts, {}, method="pre")["e"]
    meta_rms = rms(e, node)
    model = make_model("rmemo", context_mlp=True, scale_after_cell=True, **kw)
    params = model.init(jax.random.key(20), robots, obs)
    net, p = model.nets["actor"], {"params": params["actor"]}
    cache = model.robot_cache(params, robots)["actor"]
    parts = model._parts(robots, obs, None)
    pre = net.apply(p, parts, cache, method="pre")
    _, h = net.apply(p, model.initial_carry(64)["actor"], pre["xg"], node, method="recur")
    cell, ctx = rms(np.sqrt(128) * h, node), rms(take(cache["ctx"], parts["robot"]), node)
    scales = dict(meta=meta_rms, cell=cell, ctx=ctx)
    assert meta_rms > 2.0 and cell + ctx < meta_rms / 3, scales
    assert ctx < 0.5 * cell, scales
    assert np.sqrt(128) * ctx > 2.0 * cell, scales                     # with scale_context=True


def test_flat_terrain_model_runs_without_height_map():
    model, robots, params, step, _ = setup("rmomo", hfield=False)
    obs = make_obs(9, (B,))._replace(hfield=None)
    mu, v, _ = step(params, robots, obs, model.initial_carry(B), jnp.ones(B, bool))
    assert mu.shape == (B, 24) and np.all(np.isfinite(np.asarray(v)))
    assert "hfield_encoder" not in params["actor"]


def test_dict_observations_and_batch_shapes():
    model, robots, params, step, _ = setup("rmomo")
    obs = make_obs(10, (2, 2))
    carry = model.initial_carry((2, 2))
    mu, v, c = fast_jit(model.step)(params, robots, obs._asdict(), carry, jnp.zeros((2, 2), bool))
    mu_f, v_f, _ = step(params, robots, jax.tree.map(lambda x: x.reshape(4, *x.shape[2:]), obs),
                        model.initial_carry(4), jnp.zeros(4, bool))
    assert mu.shape == (2, 2, 24) and c["actor"]["h"].shape == (2, 2, NUM_TOKENS, 16)
    assert_close(mu.reshape(4, 24), mu_f)
    assert_close(v.reshape(4), v_f)


# ---------------------------------------------------------------------------------------------- initialisation
def test_initialisation():
    model, robots, _, _, _ = setup("metamorph")
    params = fast_jit(model.init)(jax.random.key(1, impl="rbg"), robots, make_obs(0, (B,)))
    a = params["actor"]
    assert np.abs(a["embed"]["kernel"]).max() <= 0.1
    dec = a["decoder"][f"layers_{len(a['decoder']) - 1}"]
    assert np.abs(dec["kernel"]).max() <= 0.01 and np.all(dec["bias"] == 0)
    assert_tree_close(a["layers_0"], a["layers_1"], 0)                      # PyTorch clones the layer
    assert np.all(a["layers_0"]["in_proj_bias"] == 0) and np.all(a["layers_0"]["out_proj"]["bias"] == 0)
    assert not np.allclose(a["embed"]["kernel"], params["critic"]["embed"]["kernel"])  # separate networks

    model, robots, _, _, _ = setup("modumorph")
    params = fast_jit(model.init)(jax.random.key(1, impl="rbg"), robots, make_obs(0, (B,)))
    a = params["actor"]
    for head in ("hn_embed_w", "hn_embed_b", "hn_dec_w_0", "hn_dec_b_0"):
        assert np.all(a[head]["kernel"] == 0), head
    assert 0.05 < np.abs(a["hn_embed_w"]["bias"]).max() <= 0.1
    assert 0.005 < np.abs(a["hn_dec_w_1"]["bias"]).max() <= 0.01
    assert np.all(a["hn_embed_b"]["bias"] == 0) and np.all(a["hn_dec_b_1"]["bias"] == 0)
    assert np.abs(a["fa_encoder"]["layers_0"]["kernel"]).max() <= 0.1
    assert np.abs(a["hn_encoder"]["layers_0"]["kernel"]).max() <= 0.1
    assert 0.1 < np.abs(a["hn_encoder"]["layers_1"]["kernel"]).max() <= 1 / np.sqrt(16)   # PyTorch default


# ---------------------------------------------------------------------------------------------- reference
def _ln(x, p):
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + 1e-5) * p["scale"] + p["bias"]


def _lin(x, p):
    return x @ p["kernel"] + p["bias"]


def _mlp(x, p, final_relu):
    n = len(p)
    for i in range(n):
        x = _lin(x, p[f"layers_{i}"])
        if i < n - 1 or final_relu:
            x = np.maximum(x, 0)
    return x


def _softmax_rows(logits, mask):
    logits = np.where(mask[None, None, :], logits, -np.inf)
    e = np.exp(logits - logits.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def _ref_net(p, fixed, o, ctx, mask, hf, d, heads):
    """NumPy forward of one MetaMorph / ModuMorph network for one sample, written from the original models' equations."""
    dh = d // heads
    split = lambda x: x.reshape(12, heads, dh).transpose(1, 0, 2)             # noqa: E731
    if fixed:
        c_hn = _mlp(ctx, p["hn_encoder"], True)
        c_fa = _mlp(ctx, p["fa_encoder"], True)
        w = _lin(c_hn, p["hn_embed_w"]).reshape(12, 52, d)
        x = (np.einsum("li,lio->lo", o, w) + _lin(c_hn, p["hn_embed_b"])) * np.sqrt(d)
    else:
        x = _lin(o, p["embed"]) * np.sqrt(d)
    i = 0
    while f"layers_{i}" in p:
        lp = p[f"layers_{i}"]
        wi, bi = lp["in_proj_kernel"], lp["in_proj_bias"]
        y = _ln(x, lp["norm1"])
        src_qk = _ln(c_fa, lp["norm_context"]) if fixed else y
        q = src_qk @ wi[:, :d] + bi[:d]
        k = src_qk @ wi[:, d:2 * d] + bi[d:2 * d]
        v = y @ wi[:, 2 * d:] + bi[2 * d:]
        probs = _softmax_rows(np.einsum("hqd,hkd->hqk", split(q), split(k)) / np.sqrt(dh), mask)
        att = np.einsum("hqk,hkd->hqd", probs, split(v)).transpose(1, 0, 2).reshape(12, d)
        x = x + _lin(att, lp["out_proj"])
        y = _ln(x, lp["norm2"])
        x = x + _lin(np.maximum(_lin(y, lp["linear1"]), 0), lp["linear2"])
        i += 1
    x = np.concatenate([x, np.repeat(_mlp(hf, p["hfield_encoder"], True)[None], 12, 0)], -1)
    if not fixed:
        return _mlp(x, p["decoder"], False)
    k = 0
    while f"hn_dec_w_{k}" in p:
        a, b = x.shape[-1], p[f"hn_dec_b_{k}"]["bias"].shape[0]
        w = _lin(c_hn, p[f"hn_dec_w_{k}"]).reshape(12, a, b)
        x = np.einsum("li,lio->lo", x, w) + _lin(c_hn, p[f"hn_dec_b_{k}"])
        k += 1
        if f"hn_dec_w_{k}" in p:
            x = np.maximum(x, 0)
    return x


@pytest.mark.parametrize("arch", ["metamorph", "modumorph"])
def test_against_numpy_reference(arch):
    model, robots, params, step, _ = setup(arch)
    obs = make_obs(11, (B,))
    mu, v, _ = step(params, robots, obs, {}, jnp.zeros(B, bool))
    p64 = jax.tree.map(lambda x: np.asarray(x, np.float64), params)
    for n in range(B):
        r = int(obs.robot[n])
        args = (np.asarray(obs.proprio[n], np.float64), np.asarray(robots.context[r], np.float64),
                np.asarray(robots.node_mask[r]), np.asarray(obs.hfield[n], np.float64), 16, 2)
        out_a = _ref_net(p64["actor"], arch == "modumorph", *args).reshape(24)
        out_c = _ref_net(p64["critic"], arch == "modumorph", *args)[:, 0]
        act = np.asarray(robots.act_mask[r])
        node = np.asarray(robots.node_mask[r])
        assert_close(mu[n], np.where(act, out_a, 0.0), 1e-4)
        assert_close(v[n], out_c[node].mean(), 1e-4)


def test_cells_match_pytorch_equations():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 5)).astype(np.float32)
    h0 = rng.normal(size=(3, 4)).astype(np.float32)
    c0 = rng.normal(size=(3, 4)).astype(np.float32)
    sig = lambda z: 1 / (1 + np.exp(-z))                                     # noqa: E731

    cell = LSTMCell(5, 4)
    p = cell.init(jax.random.key(0), {"h": h0, "c": c0}, x, method=lambda m, s, x: m.recur(s, m.input_proj(x)))
    st, h = cell.apply(p, {"h": h0, "c": c0}, x, method=lambda m, s, x: m.recur(s, m.input_proj(x)))
    q = {k: np.asarray(v) for k, v in p["params"].items()}
    g = x @ q["w_ih"] + q["b_ih"] + h0 @ q["w_hh"] + q["b_hh"]
    i, f, gg, o = np.split(g, 4, -1)
    c1 = sig(f) * c0 + sig(i) * np.tanh(gg)
    assert_close(st["c"], c1)
    assert_close(h, sig(o) * np.tanh(c1))
    assert sum(v.size for v in q.values()) == 4 * 4 * (5 + 4 + 2)
    assert np.abs(q["w_ih"]).max() <= 0.5                                    # U(+-1/sqrt(H))

    cell = GRUCell(5, 4)
    p = cell.init(jax.random.key(0), {"h": h0}, x, method=lambda m, s, x: m.recur(s, m.input_proj(x)))
    st, h = cell.apply(p, {"h": h0}, x, method=lambda m, s, x: m.recur(s, m.input_proj(x)))
    q = {k: np.asarray(v) for k, v in p["params"].items()}
    xi, hh = x @ q["w_ih"] + q["b_ih"], h0 @ q["w_hh"] + q["b_hh"]
    r = sig(xi[:, :4] + hh[:, :4])
    z = sig(xi[:, 4:8] + hh[:, 4:8])
    n = np.tanh(xi[:, 8:] + r * hh[:, 8:])
    assert_close(h, (1 - z) * n + z * h0)
    assert sum(v.size for v in q.values()) == 3 * 4 * (5 + 4 + 2)


def test_state_features():
    assert list(STATE_FEATURES) == [*range(13), 30, 31, 41, 42]


# ---------------------------------------------------------------------------------------------- distribution
def test_distribution():
    rng = np.random.default_rng(0)
    mu = jnp.asarray(rng.normal(size=(5, 24)), jnp.float32)
    a = jnp.asarray(rng.normal(size=(5, 24)), jnp.float32)
    mask = jnp.asarray(rng.random((5, 24)) < 0.6)
    std = 0.9
    ref = -0.5 * ((a - mu) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)
    assert_close(distribution.log_prob(mu, a, mask), np.where(mask, ref, 0).sum(-1))
    ent = 0.5 + 0.5 * np.log(2 * np.pi) + np.log(std)
    assert_close(distribution.entropy(mu, mask), np.asarray(mask).sum(-1) * ent)
    assert_close(distribution.entropy_metamorph(mu, mask), np.where(mask, ent, 0).mean())
    s = distribution.sample(jax.random.key(0), jnp.zeros((20000, 24)))
    assert abs(float(s.std()) - std) < 0.01
    s = distribution.sample(jax.random.key(0), mu, act_mask=mask)
    assert np.all(np.asarray(s)[~np.asarray(mask)] == 0)
    assert_close(distribution.kl_divergence(mu, mu, mask), np.zeros(5))


# ---------------------------------------------------------------------------------------------- configs / CLI
def test_make_model_rejects_unknown_options():
    with pytest.raises(ValueError, match="unknown architecture"):
        make_model("transformer", hfield=False, decoder_dims=[])
    with pytest.raises(ValueError, match="inapplicable"):
        make_model("metamorph", hfield=False, decoder_dims=[], cell_residual=True)
    with pytest.raises(ValueError, match="inapplicable"):
        make_model("rmomo", hfield=False, decoder_dims=[], d_modle=32)
    with pytest.raises(ValueError, match="must equal d_model"):
        make_model("rmemo", hfield=False, decoder_dims=[], hidden=64)


def test_params_cli():
    from experiments import params as cli
    for arch in ARCHS:
        assert cli.model_of(arch, "ft").arch == arch
    out = subprocess.run([sys.executable, "-m", "experiments.params", "env=ft"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = {ln.split()[0]: ln.split() for ln in out.stdout.splitlines() if ln and not ln.startswith("#")}
    for arch in ARCHS:
        assert int(lines[arch][1]) == FT_COUNTS[arch]
    assert "5232774" in " ".join(lines["modumorph"]) and "5563526" in " ".join(lines["rmomo"])
    # a run of rmemo gets the measured context MLP and scale placement (nets.zoo.RECOMMENDED): the note gives the
    # count a run has (the scale adds no parameter)
    assert "context_mlp=True, scale_after_cell=True, scale_context=True: 3610499, +42240" in " ".join(lines["rmemo"])
    assert "a run" not in " ".join(lines["metamorph"])
    bad = subprocess.run([sys.executable, "-m", "experiments.params", "env=ft", "no_such_key=1"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "no_such_key" in bad.stderr


@pytest.mark.parametrize("arch", ["metamorph", "rmemo"])
def test_attention_through_dot_product_attention_is_the_same_function(arch):
    """attention=xla (jax.nn.dot_product_attention, no head transposes) gives the default einsum attention's actions and
    values, padded limbs included, in float32; the flag is refused where there is no self-attention, and an unknown
    value is refused by name."""
    model, robots, params, _, seq = setup(arch)
    other, _, params2, _, seq2 = setup(arch, flags=(("attention", "xla"),))
    assert jax.tree.structure(params) == jax.tree.structure(params2)
    obs, resets, carry = make_obs(4, (T, B)), random_resets(4), random_carry(model, 4)
    mu1, v1, c1 = seq(params, robots, obs, carry, resets, burn_in=0)
    mu2, v2, c2 = seq2(params, robots, obs, carry, resets, burn_in=0)
    assert_close(mu1, mu2)
    assert_close(v1, v2)
    assert_tree_close(c1, c2)
    with pytest.raises(ValueError, match="inapplicable"):
        make_model("modumorph", hfield=False, decoder_dims=[], attention="xla")
    with pytest.raises(ValueError, match="attention='flash'; expected one of einsum, xla, cudnn"):
        make_model("metamorph", hfield=False, decoder_dims=[], attention="flash")


def test_dot_product_attention_mask_spans_the_query_axis(monkeypatch):
    """The key mask reaches `jax.nn.dot_product_attention` as [batch, 1, queries, keys] with the query axis full:
    cuDNN's kernel (attention=cudnn, GPU only) refuses a mask broadcast over the queries (it failed so in session
    38), so this CPU test holds the shape it needs, and the result still masks the padded keys."""
    from mjx_morph.nets.layers import dot_product_attention
    seen = []
    real = jax.nn.dot_product_attention

    def spy(q, k, v, mask=None, implementation=None, **kw):
        seen.append(mask.shape)
        return real(q, k, v, mask=mask, implementation=None, **kw)
    monkeypatch.setattr(jax.nn, "dot_product_attention", spy)
    t, d, heads = 5, 8, 2
    q, k, v = (jax.random.normal(jax.random.PRNGKey(i), (3, t, d)) for i in range(3))
    keep = jnp.array([[1, 1, 1, 0, 0]] * 3, bool)
    out = dot_product_attention(q, k, v, keep, heads, "cudnn")
    assert seen == [(3, 1, t, t)]
    # padded keys carry no weight: changing their values changes nothing
    v2 = v.at[:, 3:].set(100.0)
    np.testing.assert_allclose(out, dot_product_attention(q, k, v2, keep, heads, "xla"), rtol=1e-5, atol=1e-5)
