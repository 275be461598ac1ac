"""The algorithm's settings: one dataclass, the one home of every PPO default (`experiments.run ppo.<key>=...`)."""
from __future__ import annotations

import dataclasses
from typing import Optional


@dataclasses.dataclass
class PPOConfig:
    num_envs: int = 1024            # parallel envs
    rollout_len: int = 80           # control steps per env per iteration (a multiple of the window);
                                    # 1024 x 80 = the paper's 81,920 transitions (32 envs x 2560 steps) per iteration
    window: int = 80                # training window of recurrent models (feed-forward models: 1)
    burn_in: int = 20               # burn-in prefix of each window (feed-forward models: 0)
    minibatch_size: int = 5120      # transitions per minibatch (= 64 windows of 80)
    epochs: int = 8
    gamma: float = 0.99
    lam: float = 0.95
    clip_eps: float = 0.2
    value_coef: float = 0.5
    entropy_coef: float = 0.0
    lr: float = 3e-4
    warmup_iters: int = 5
    adam_eps: float = 1e-5
    max_grad_norm: float = 0.5
    kl_threshold: float = 0.05      # approximate-KL early stop (0.05 = MetaMorph's KL_TARGET_COEF 5; the paper also uses 0.03
                                    # and picks per model on val: all four models keep 0.05, two seeds an
                                    # arm; docs/results-log.md, sessions 34-38)
    sampling: str = "balanced"      # robot sampling at resets: balanced | uniform
    minibatch_blocks: Optional[int] = None   # G: each minibatch takes 1/G of its windows from each of G equal blocks
                                    # of envs (stratified); None: the devices the envs are sharded over, so one device
                                    # keeps the plain uniform shuffle (G = 1) and each of several computes its own
                                    # share of a minibatch (data parallel, gradients summed across devices)

    @property
    def steps_per_iter(self) -> int:
        return self.num_envs * self.rollout_len

    def iterations(self, total_steps: int) -> int:
        """Iterations of a `total_steps` schedule (at least one)."""
        return max(1, int(total_steps) // self.steps_per_iter)

    def for_model(self, recurrent: bool) -> "PPOConfig":
        """Feed-forward models train on single transitions (W = 1, B = 0), as the original PPO."""
        return self if recurrent else dataclasses.replace(self, window=1, burn_in=0)

    def check_values(self) -> None:
        """Refuse values no model can run with (ValueError naming the key and what was expected)."""
        for key in ("num_envs", "rollout_len", "window", "minibatch_size", "epochs"):
            if getattr(self, key) < 1:
                raise ValueError(f"ppo.{key}={getattr(self, key)}: expected a positive integer")
        if self.burn_in < 0:
            raise ValueError(f"ppo.burn_in={self.burn_in}: expected 0 or more")
        for key in ("gamma", "lam"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"ppo.{key}={getattr(self, key)}: expected a value in [0, 1]")
        if self.lr <= 0 or self.clip_eps <= 0:
            raise ValueError(f"ppo.lr={self.lr}, ppo.clip_eps={self.clip_eps}: expected positive values")
        if self.minibatch_blocks is not None and self.minibatch_blocks < 1:
            raise ValueError(f"ppo.minibatch_blocks={self.minibatch_blocks}: expected a positive integer or null")
        if self.sampling not in ("balanced", "uniform"):
            raise ValueError(f"ppo.sampling={self.sampling}: expected balanced or uniform")

    def check(self) -> None:
        """Refuse settings the algorithm cannot run, the window geometry included (call on `for_model`'s result)."""
        self.check_values()
        if self.rollout_len % self.window:
            raise ValueError(f"ppo.rollout_len={self.rollout_len} must be a multiple of ppo.window={self.window}")
        if self.minibatch_size % self.window:
            raise ValueError(f"ppo.minibatch_size={self.minibatch_size} must be a multiple of ppo.window={self.window}")
        if self.burn_in > self.window:
            raise ValueError(f"ppo.burn_in={self.burn_in} exceeds ppo.window={self.window}: the rollout stores the "
                             "recurrent state where each window's burn-in starts, which must lie in the window before")
        windows = self.num_envs * self.rollout_len // self.window
        if windows < self.minibatch_size // self.window:
            raise ValueError(f"a rollout has {windows} windows, fewer than one minibatch "
                             f"({self.minibatch_size // self.window} windows): lower ppo.minibatch_size")
