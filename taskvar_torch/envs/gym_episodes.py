"""The episode keys of a one-environment Gymnasium env (``WindyGridGymEnv``, ``TaxiGymEnv``).

A seed fixes a stream of episodes: episode ``k`` after ``reset(seed=s)`` draws from the keyed
stream ``(s, sub-env 0, episode k)`` (:mod:`taskvar_torch.rng`), the key the batched env's
sub-environment 0 uses, so a Gymnasium episode replays the batched one. Without a seed, the first
reset draws one from Gymnasium's ``np_random`` (entropy) and later resets continue that stream,
as Gymnasium's own envs do.
"""

from __future__ import annotations

import numpy as np
import torch

from taskvar_torch import rng


class EpisodeKeys:
    """The keys of a Gymnasium env's successive episodes (``base`` None until the first reset)."""

    def __init__(self) -> None:
        self.base: np.ndarray | None = None
        self.episode = -1

    def next(self, seed: int | None, np_random: np.random.Generator) -> torch.Tensor:
        """The next episode's key ``(1,)``; ``seed`` (checked) restarts the stream at episode 0."""
        if seed is None and self.base is None:  # first reset unseeded: Gymnasium's entropy
            seed = int(np_random.integers(0, rng.MAX_SEED + 1))
        if seed is not None:
            self.base = np.asarray(rng.sub_env_key(seed, np.zeros(1, dtype=np.int64)))
            self.episode = -1
        self.episode += 1
        return torch.as_tensor(rng.episode_key(self.base, self.episode))
