"""A conservative estimate of the memory a config will allocate, checked before allocating
(docs/reliability.md#memory-estimated-before-it-is-allocated): :func:`estimate` adds up upper
bounds by the config key that drives each term (``env.<family>``, ``env.num_envs``,
``train.buffer_size``, ``heads.hidden``, ``train.batch_size``, ``--episodes``);
:func:`check_memory` refuses a config over the memory available now in one line naming the
largest term's key.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

Config = Any  # taskvar_torch.config.Config (this module is imported by the config package)

FLOAT = 4
"""Bytes of a float32 value."""
ROW_EXTRA = 512
"""Bytes of a transition besides its two observations (keys, actions, rewards, flags, modes)."""
PARAM_COPIES = 7
"""Copies of every weight a training run holds: weights, gradients, targets, Adam's two moments,
the evaluation average and one spare."""
HEADS = 7
"""Networks per bundle (averaging, options, switching, max-value gap, robustness, a critic, the
informed head)."""
OUTPUTS = 64
"""Output width assumed for a head's last layer (options x actions: 12 to 27 in the families)."""
FIRST_VISIT_BUCKETS = 1 << 14
"""Bytes of an environment's first-visit flags (``FirstVisitFilter``'s buckets)."""
RESULT_ROW = 2048
"""Bytes of one episode's result row in an evaluation (a Python dict per CSV row)."""


def observation_size(cfg: Config) -> int:
    """The length of ``cfg``'s observation: the family's ``observation_size`` where it has one,
    else read from a one-environment env."""
    from taskvar_torch import keys
    from taskvar_torch.contract import family

    fam = family(cfg)
    if fam.observation_size is not None:
        return int(fam.observation_size(cfg))
    env = fam.make_env(cfg, 1)
    return int(env.observation_spec[keys.OBSERVATION].shape[-1])


def estimate(
    cfg: Config,
    *,
    training: bool = True,
    episodes: int = 0,
    episodes_key: str = "--episodes",
    obs_dim: int | None = None,
) -> dict[str, int]:
    """Bytes ``cfg`` will allocate at once, by the config key that drives each term.

    Args:
        cfg: the config.
        training: a training run (replay, optimiser, the collected batch); ``False``: an
            evaluation of ``eval.batch_size`` environments.
        episodes: result rows an evaluation keeps (episodes x points x methods).
        episodes_key: the key or flag that sets them, named by :func:`check_memory`.
        obs_dim: the observation's length (default :func:`observation_size`).
    """
    from taskvar_torch.contract import family

    D = observation_size(cfg) if obs_dim is None else int(obs_dim)
    fam = family(cfg)
    cells = int(fam.cells(cfg)) if fam.cells is not None else 0
    t = cfg.train
    seeds = int(t.seeds) if training else 1
    row = 2 * D * FLOAT + ROW_EXTRA
    envs = cfg.env.num_envs * seeds if training else cfg.eval.batch_size
    terms = {f"env.{fam.name}": cells * D * FLOAT, "env.num_envs": envs * row * 4}
    widths = [D, *cfg.heads.hidden, OUTPUTS]
    params = sum((a + 1) * b for a, b in zip(widths, widths[1:])) * HEADS * seeds
    copies = PARAM_COPIES if training else 1
    batch = t.batch_size * seeds if training else cfg.eval.batch_size
    terms["heads.hidden"] = params * FLOAT * copies
    # a batch's activations: named by the batch size, which they grow with as much as the widths
    batch_key = "train.batch_size" if training else "eval.batch_size"
    terms[batch_key] = terms.get(batch_key, 0) + batch * sum(widths) * FLOAT * HEADS * 4
    if training:
        terms["env.num_envs"] += t.frames_per_batch * seeds * row * 2  # batch and its n-step copy
        if t.first_visit:  # heads/first_visit.py: a bool per hash bucket per environment
            terms["env.num_envs"] += envs * FIRST_VISIT_BUCKETS
        terms["train.buffer_size"] = t.buffer_size * seeds * row
    if episodes:
        terms[episodes_key] = int(episodes) * RESULT_ROW
    return terms


def available_memory() -> int | None:
    """Bytes of memory available now: Linux ``MemAvailable``, or the cgroup's free limit where it
    is lower; ``None`` where neither can be read."""
    found = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = Path("/sys/fs/cgroup/memory.current").read_text().strip()
        if limit != "max":
            found.append(max(int(limit) - int(used), 0))
    except (OSError, ValueError):
        pass
    if not found:
        try:
            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (OSError, ValueError, AttributeError):
            return None
    return min(found)


def size_text(n: float) -> str:
    """``n`` bytes in B, kB, MB, GB, TB or PB."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} PB"


def check_memory(terms: dict[str, int], available: int | None = None) -> None:
    """A one-line ``ValueError`` when the ``terms`` (:func:`estimate`) add up to more than the
    memory ``available`` (default :func:`available_memory`; unknown: no check), naming the
    largest term's key and both sizes."""
    available = available_memory() if available is None else available
    total = sum(terms.values())
    if available is None or total <= available:
        return
    key = max(terms, key=terms.get)
    raise ValueError(
        f"{key} asks for too much memory: the run would need about {size_text(total)} "
        f"({key}: {size_text(terms[key])}), {size_text(available)} is available here; lower {key}"
    )


__all__ = ["available_memory", "check_memory", "estimate", "observation_size", "size_text"]
