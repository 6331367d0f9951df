"""Heads: the learnt functions of the paper as networks, and their learners (docs/design.md)."""

from taskvar_torch.heads.bundle import HEAD_NAMES, HEAD_OUT_KEYS, Heads

__all__ = ["HEAD_NAMES", "HEAD_OUT_KEYS", "Heads"]
