"""Counter-based random numbers: keyed, batched, identical on every device and batch split
(docs/design.md#randomness-keyed-not-a-shared-generator).

Every sub-env episode has an integer key and draws ``bits = hash(key, counter)``. Keys are uint32;
the generic functions take Python ints, numpy ``int64`` and torch ``int64``; the ``*_i32``
hot-path versions take torch ``int32`` and agree bit for bit.
"""

from __future__ import annotations

import operator

import torch

MASK32 = 0xFFFFFFFF
_GOLDEN = 0x9E3779B9  # Weyl increment (2^32 / golden ratio)
_M1, _M2 = 0x7FEB352D, 0x846CA68B  # lowbias32 multipliers (C. Wellons)
_INV24 = 1.0 / (1 << 24)

# Counters at and above RESET_COUNTER are reserved for draws made at reset (instance, start cell);
# step ``t`` of an episode uses counters below it.
RESET_COUNTER = 1 << 30


def hash32(x):
    """lowbias32 integer hash on values holding uint32s (int / int64 array / int64 tensor)."""
    if isinstance(x, torch.Tensor) and x.dtype == torch.int64:
        x = x ^ (x >> 16)  # a fresh tensor: the steps below update it in place (fewer allocations)
        x.mul_(_M1).bitwise_and_(MASK32)
        x.bitwise_xor_(x >> 15)
        x.mul_(_M2).bitwise_and_(MASK32)
        return x.bitwise_xor_(x >> 16)
    x = x ^ (x >> 16)
    x = (x * _M1) & MASK32
    x = x ^ (x >> 15)
    x = (x * _M2) & MASK32
    return x ^ (x >> 16)


def draw_bits(key, counter):
    """32 random bits for ``(key, counter)``; ``key`` and ``counter`` broadcast."""
    return hash32((key + counter * _GOLDEN) & MASK32)


def draw_uniform(key, counter):
    """Uniform in [0, 1) on the 24-bit grid ``k / 2^24``, for ``(key, counter)``."""
    return uniform_of(draw_bits(key, counter))


def draw_index(key, counter, n):
    """Uniform integer in ``[0, n)`` for ``(key, counter)`` (n < 2^24)."""
    return index_of(draw_bits(key, counter), n)


def uniform_of(bits):
    """:func:`draw_uniform` from the :func:`draw_bits` of the same ``(key, counter)``."""
    bits = bits >> 8
    if isinstance(bits, torch.Tensor):
        return bits.to(torch.float32) * _INV24
    if isinstance(bits, int):
        return bits * _INV24
    return bits.astype("float32") * _INV24


def index_of(bits, n):
    """:func:`draw_index` from the :func:`draw_bits` of the same ``(key, counter)``."""
    return ((bits >> 8) * n) >> 24


def probability_threshold(p: torch.Tensor) -> torch.Tensor:
    """int32 threshold ``ceil(p * 2^24)`` so that ``(bits >> 8) < threshold`` iff ``u < p`` exactly."""
    return torch.ceil(p.to(torch.float64) * (1 << 24)).to(torch.int32)


MAX_SEED = MASK32
"""Largest seed: keys are 32 bits, so seeds are integers in ``[0, 2**32 - 1]``, each its own
stream (a larger one is refused, never wrapped onto another seed's streams)."""


def check_seed(seed, key: str = "seed") -> int:
    """``seed`` as a Python int when it is an integer (not a bool) in ``[0, MAX_SEED]``, else a
    one-line ``ValueError`` naming ``key``."""
    try:
        value = None if isinstance(seed, bool) else operator.index(seed)
    except TypeError:
        value = None
    if value is None or not 0 <= value <= MAX_SEED:
        raise ValueError(f"{key} must be an integer in [0, {MAX_SEED}] (2**32 - 1), got {seed!r}")
    return value


def sub_env_key(seed: int, index):
    """Base key of global sub-env ``index`` under ``seed``; a ``seed`` outside ``[0, 2**32 - 1]`` is
    a ``ValueError``."""
    return hash32((hash32(check_seed(seed)) + index * _GOLDEN) & MASK32)


def episode_key(base_key, episode):
    """Key of episode number ``episode`` of the sub-environment with ``base_key``."""
    return hash32(base_key ^ hash32((episode + 0x632BE5AB) & MASK32))  # both sides uint32


def to_i32(key: torch.Tensor) -> torch.Tensor:
    """uint32 values held in int64 -> the same bit pattern in int32."""
    return (key - ((key >> 31) << 32)).to(torch.int32)


def draw_bits_i32(key: torch.Tensor, counter: torch.Tensor | int) -> torch.Tensor:
    """:func:`draw_bits` on int32 keys/counters; returns the uint32 bit pattern as int32."""
    x = torch.add(key, counter, alpha=_GOLDEN - (1 << 32))  # int32 wrapping arithmetic
    # logical shifts: mask off the sign-extended bits; in place on the fresh x (fewer allocations)
    x.bitwise_xor_((x >> 16).bitwise_and_(0xFFFF))
    x.mul_(_M1)
    x.bitwise_xor_((x >> 15).bitwise_and_(0x1FFFF))
    x.mul_(_M2 - (1 << 32))
    return x.bitwise_xor_((x >> 16).bitwise_and_(0xFFFF))


def bernoulli_i32(
    key: torch.Tensor, counter: torch.Tensor | int, threshold: torch.Tensor
) -> torch.Tensor:
    """``u(key, counter) < p`` with ``threshold = probability_threshold(p)``: bool, hot path."""
    return draw_bits_i32(key, counter).bitwise_right_shift_(8).bitwise_and_(0xFFFFFF) < threshold
