"""Counter-based random numbers: keyed, batched, identical on every device and batch split.

A ``torch.Generator`` hands out one stream per *batch*, so a sub-environment's draws would change
with the number of environments it is batched with. Like Gymnax/JAX keys, we instead give every
sub-environment episode an integer key and draw ``u = hash(key, counter)``: the draw depends only on
(seed, sub-environment index, episode, step), never on N, the device or the order of calls. That
gives bit-identical trajectories whatever N is split into, and common random numbers for paired
evaluation (SPEC §5) for free. Works on numpy ``int64`` arrays and torch ``int64`` tensors alike.
"""

from __future__ import annotations

MASK32 = 0xFFFFFFFF
_GOLDEN = 0x9E3779B9  # Weyl increment (2^32 / golden ratio)
_INV24 = 1.0 / (1 << 24)

# Counters at and above RESET_COUNTER are reserved for draws made at reset (instance, start cell);
# step ``t`` of an episode uses counter ``t``.
RESET_COUNTER = 1 << 30


def hash32(x):
    """lowbias32 integer hash (C. Wellons) on int64 values holding uint32s; returns uint32 in int64."""
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & MASK32
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & MASK32
    return x ^ (x >> 16)


def draw_bits(key, counter):
    """32 random bits for ``(key, counter)``; ``key`` and ``counter`` broadcast."""
    return hash32((key + counter * _GOLDEN) & MASK32)


def draw_uniform(key, counter):
    """Uniform float in [0, 1) with 24 random bits, for ``(key, counter)``."""
    bits = draw_bits(key, counter) >> 8
    if hasattr(bits, "to"):  # torch
        import torch

        return bits.to(torch.float32) * _INV24
    return bits.astype("float32") * _INV24


def draw_index(key, counter, n):
    """Uniform integer in ``[0, n)`` for ``(key, counter)`` (n may be a tensor or int, n < 2^24)."""
    bits = draw_bits(key, counter) >> 8
    return (bits * n) >> 24


def sub_env_key(seed: int, index):
    """Base key of sub-environment ``index`` under ``seed`` (``index`` is global, see ``index_offset``)."""
    return hash32((hash32(seed & MASK32) + index * _GOLDEN) & MASK32)


def episode_key(base_key, episode):
    """Key of episode number ``episode`` of the sub-environment with ``base_key``."""
    return hash32((base_key ^ hash32((episode + 0x632BE5AB) & MASK32)) & MASK32)
