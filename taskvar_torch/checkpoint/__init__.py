"""Checkpoint bundles: plain data only, atomic writes, clear refusals (docs/reliability.md).

A bundle is a dict of plain data (what ``torch.load(..., weights_only=True)`` accepts, so loading
never executes code from the file): ``config`` (required), ``models``, ``optimizers``, ``counters``,
``rng`` (:func:`rng_state`), optional ``replay``, ``heads_spec`` and further entries;
:func:`save_checkpoint` adds a format tag, version and the library versions. Writes go to a
temporary file, fsynced, then ``os.replace``; every loading failure is a one-line
:class:`CheckpointError`. Checking entries against what the config builds is
:mod:`taskvar_torch.checkpoint.checks`.
"""

from __future__ import annotations

import importlib.metadata
import os
import pickle
import platform
import random
import warnings
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

import taskvar_torch
from taskvar_torch.config import Config, config_to_dict
from taskvar_torch.config.migration import migrate_config_data
from taskvar_torch.io import atomic_write

FORMAT = "taskvar_torch.checkpoint"
FORMAT_VERSION = 1
RUNTIME_KEYS = (
    "device",
    "train.total_frames",
    "train.checkpoint_every",
    "train.log_every",
    "train.logger",
    "eval",
    "experiment",
)
"""Config keys (dotted prefixes) that may differ between a checkpoint and the config resuming or
evaluating it: they change how long or where a run goes, not what the weights mean."""

_LEAVES = (str, int, float, bool, type(None), torch.dtype, torch.device)  # exact types only


class CheckpointError(ValueError):
    """A checkpoint cannot be written or read; the message is one line naming the path."""


# --------------------------------------------------------------------------------------------
# versions and RNG


def library_versions() -> dict[str, str]:
    """Versions of this package and the libraries a checkpoint depends on."""

    def version(dist: str) -> str:
        try:
            return importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            return "not installed"

    return {
        "taskvar_torch": str(taskvar_torch.__version__),
        "torch": str(torch.__version__),
        "torchrl": version("torchrl"),
        "tensordict": version("tensordict"),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def rng_state(generators: Mapping[str, torch.Generator] | None = None) -> dict[str, Any]:
    """Every random state a run may draw from, as plain data: ``{"torch", "cuda" (list), "numpy",
    "python", "generators": {name: state}}`` for the named ``generators``.
    """
    name, keys, pos, has_gauss, cached = np.random.get_state()
    version, mt, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": {
            "bit_generator": str(name),
            "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached),
        },
        "python": {"version": int(version), "state": list(mt), "gauss_next": gauss_next},
        "generators": {k: g.get_state() for k, g in (generators or {}).items()},
    }


def set_rng_state(
    state: Mapping[str, Any], generators: Mapping[str, torch.Generator] | None = None
) -> None:
    """Restore what :func:`rng_state` returned (CUDA states only where CUDA is available); every
    named generator must be in ``state``.
    """
    torch.set_rng_state(state["torch"].cpu())
    cuda = state.get("cuda") or []
    if cuda and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in cuda[: torch.cuda.device_count()]])
    n = state["numpy"]
    np.random.set_state(
        (
            n["bit_generator"],
            n["keys"].cpu().numpy().astype(np.uint32),
            n["pos"],
            n["has_gauss"],
            n["cached_gaussian"],
        )
    )
    p = state["python"]
    random.setstate((p["version"], tuple(p["state"]), p["gauss_next"]))
    saved = state.get("generators", {})
    for k, g in (generators or {}).items():
        if k not in saved:
            raise CheckpointError(f"no state for generator {k!r}; saved: {sorted(saved)}")
        g.set_state(saved[k].cpu())


# --------------------------------------------------------------------------------------------
# bundles


def _state_dict(x: nn.Module | torch.optim.Optimizer | Mapping) -> Mapping:
    return x.state_dict() if hasattr(x, "state_dict") else x


def make_bundle(
    config: Config | Mapping[str, Any],
    models: Mapping[str, nn.Module | Mapping[str, Any]],
    optimizers: Mapping[str, torch.optim.Optimizer | Mapping[str, Any]] | None = None,
    counters: Mapping[str, int | float] | None = None,
    rng: Mapping[str, Any] | None = None,
    replay: Mapping[str, Any] | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """A bundle with the conventional keys (modules and optimizers become state dicts; ``rng``
    defaults to :func:`rng_state` now; ``**extra``: further plain-data entries).
    """
    bundle = {
        "config": config_to_dict(config) if isinstance(config, Config) else dict(config),
        "models": {k: _state_dict(m) for k, m in models.items()},
        "optimizers": {k: _state_dict(o) for k, o in (optimizers or {}).items()},
        "counters": dict(counters or {}),
        "rng": dict(rng) if rng is not None else rng_state(),
        **extra,
    }
    if replay is not None:
        bundle["replay"] = dict(replay)
    return bundle


def _check_plain(obj: Any, where: str) -> None:
    """Raise CheckpointError naming the first entry that ``weights_only`` loading would refuse."""
    if type(obj) in (torch.Tensor, nn.Parameter, *_LEAVES):  # not subclasses: str(TorchVersion)
        return
    if type(obj) in (dict, OrderedDict):
        for k, v in obj.items():
            if not isinstance(k, (str, int)):
                raise CheckpointError(
                    f"{where} has a key of type {type(k).__name__}: use str or int"
                )
            _check_plain(v, f"{where}[{k!r}]")
        return
    if type(obj) in (list, tuple, torch.Size):
        for i, v in enumerate(obj):
            _check_plain(v, f"{where}[{i}]")
        return
    if isinstance(obj, torch.Tensor):
        raise CheckpointError(
            f"{where} is a tensor subclass {type(obj).__qualname__}; store "
            "x.as_subclass(torch.Tensor) instead"
        )
    raise CheckpointError(
        f"{where} holds a {type(obj).__module__}.{type(obj).__qualname__}; checkpoints hold plain "
        "data only (tensors, dicts, lists, str, int, float, bool, None)"
    )


def save_checkpoint(path: str | os.PathLike, bundle: Mapping[str, Any]) -> Path:
    """Write ``bundle`` (plain data with at least ``config``) atomically to ``path``; returns
    ``path``.

    Raises:
        CheckpointError: the bundle holds something other than plain data, or has no config.
        OSError: the write failed, its ``filename`` set to ``path``.

    On either error the file at ``path`` is left untouched and no temporary file remains.
    """
    path = Path(path)
    if not isinstance(bundle, Mapping):
        raise CheckpointError(
            f"cannot save {str(path)!r}: a bundle is a dict, got {type(bundle).__name__}"
        )
    if "config" not in bundle:
        raise CheckpointError(f"cannot save {str(path)!r}: the bundle has no 'config' entry")
    for k in ("format", "format_version"):
        if k in bundle:
            raise CheckpointError(f"cannot save {str(path)!r}: {k!r} is reserved; remove it")
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "versions": library_versions()}
    data.update(bundle)
    if isinstance(data["config"], Config):
        data["config"] = config_to_dict(data["config"])
    try:
        _check_plain(data, "bundle")
    except CheckpointError as e:
        raise CheckpointError(f"cannot save {str(path)!r}: {e}") from None
    try:
        atomic_write(path, lambda f: _torch_save(data, f))
    except OSError as e:  # disk full, file too large: path keeps its old content, no temp file
        if e.filename is None and e.errno is not None:  # the CLI's line names it: cannot use PATH
            e.filename = str(path)
        raise
    return path


class _WriteErrors:
    """A file's ``write``/``flush`` that keep the first ``OSError`` (torch's zip writer hides it),
    for :func:`_torch_save` to raise.
    """

    def __init__(self, f: Any) -> None:
        self.f, self.error = f, None

    def write(self, b: Any) -> int:
        try:
            return self.f.write(b)
        except OSError as e:
            self.error = self.error or e
            raise

    def flush(self) -> None:
        self.f.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.f, name)


def _torch_save(data: Any, f: Any) -> None:
    """``torch.save(data, f)``; a failed write raises its ``OSError`` (ENOSPC, EFBIG, EIO)."""
    sink = _WriteErrors(f)
    try:
        torch.save(data, sink)
    except RuntimeError:
        if sink.error is not None:
            raise sink.error from None
        raise


# --------------------------------------------------------------------------------------------
# loading


def first_line(e: BaseException, limit: int = 160) -> str:
    """The first line (first sentence) of an exception's message in a refusal, at most ``limit``
    characters."""
    text = str(e).strip()
    line = text.splitlines()[0].split(". ")[0] if text else type(e).__name__
    return line if len(line) <= limit else line[: limit - 3] + "..."


_GARBAGE = ("Unsupported operand", "String is too long")
"""Unpickler errors that mean the bytes are not a pickle stream (random or foreign data), as
opposed to a well-formed pickle that names code or objects."""


def _is_garbage(e: BaseException) -> bool:
    return any(marker in str(e) for marker in _GARBAGE)


def _refusal_detail(e: BaseException) -> str:
    for line in str(e).splitlines():
        line = line.replace("WeightsUnpickler error:", "").strip()
        if _is_garbage(Exception(line)):
            return line.rstrip(".")[:120]
        if "unsupported global" in line.lower() or line.startswith("Unsupported"):
            line = line.split(" was not an allowed global")[0].split(" whose module")[0]
            return line.rstrip(".")[:120]
    return "unsupported pickle content"


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, Mapping):
        return {prefix.rstrip("."): d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = list(v) if isinstance(v, tuple) else v
    return out


def config_differences(
    saved: Mapping[str, Any],
    expected: Config | Mapping[str, Any],
    ignore: Sequence[str] = RUNTIME_KEYS,
) -> list[tuple[str, Any, Any]]:
    """``(dotted key, saved, expected)`` for every differing key not under ``ignore``
    (``"<absent>"`` for a missing side); ``saved`` is migrated to the current schema first.
    """
    exp = config_to_dict(expected) if isinstance(expected, Config) else expected
    a, b = _flatten(migrate_config_data(saved, warn=False)), _flatten(exp)

    def ignored(k: str) -> bool:
        return any(k == p or k.startswith(p + ".") for p in ignore)

    missing = "<absent>"
    diffs = []
    for k in list(a) + [k for k in b if k not in a]:
        if ignored(k):
            continue
        va, vb = a.get(k, missing), b.get(k, missing)
        if va != vb:
            diffs.append((k, va, vb))
    return diffs


def load_checkpoint(
    path: str | os.PathLike,
    expected_config: Config | Mapping[str, Any] | None = None,
    map_location: str | torch.device | None = "cpu",
    ignore: Sequence[str] = RUNTIME_KEYS,
) -> dict[str, Any]:
    """Load a bundle with ``torch.load(weights_only=True)``; never executes code from the file.

    ``expected_config``: when given, the saved config must match it on every key not under
    ``ignore`` (default :data:`RUNTIME_KEYS`).

    Raises:
        CheckpointError: one line naming the problem and the path: missing, truncated or corrupt,
            containing code or objects, not a taskvar_torch checkpoint, an unreadable format
            version, or trained with a different config.
    """
    path = Path(path)
    where = repr(str(path))
    if not path.exists():
        raise CheckpointError(f"checkpoint {where} does not exist")
    if not path.is_file():
        raise CheckpointError(f"checkpoint {where} is not a file")
    try:
        with warnings.catch_warnings():  # torch's pickle-protocol notes would only add noise
            warnings.simplefilter("ignore")
            data = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        if _is_garbage(e):  # not a pickle stream at all: random bytes, another kind of file
            raise CheckpointError(
                f"checkpoint {where} is truncated or corrupt (not a torch checkpoint file: "
                f"{_refusal_detail(e)})"
            ) from None
        raise CheckpointError(
            f"refusing to load {where}: not a plain-data checkpoint (it contains code or objects: "
            f"{_refusal_detail(e)})"
        ) from None
    except PermissionError as e:
        raise CheckpointError(f"cannot read checkpoint {where}: {first_line(e)}") from None
    except Exception as e:  # RuntimeError, OSError (zip), EOFError, KeyError... from a damaged file
        raise CheckpointError(
            f"checkpoint {where} is truncated or corrupt ({type(e).__name__}: {first_line(e)})"
        ) from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        what = (
            f"a dict with keys {sorted(map(str, data))[:8]}"
            if isinstance(data, dict)
            else f"a {type(data).__name__}"
        )
        raise CheckpointError(f"{where} is not a taskvar_torch checkpoint (it holds {what})")
    version = data.get("format_version")
    if type(version) is not int or version < 1:
        raise CheckpointError(f"checkpoint {where} is corrupt: format_version is {version!r}")
    if version > FORMAT_VERSION:
        written = data.get("versions", {}).get("taskvar_torch", "?")
        raise CheckpointError(
            f"checkpoint {where} has format version {version} (written by taskvar_torch {written}); "
            f"this taskvar_torch {taskvar_torch.__version__} reads versions up to {FORMAT_VERSION}"
        )
    if not isinstance(data.get("config"), dict):
        raise CheckpointError(f"checkpoint {where} is corrupt: it has no config dict")
    _check_entry_types(data, where)
    if expected_config is not None:
        diffs = config_differences(data["config"], expected_config, ignore)
        if diffs:
            key, saved, wanted = diffs[0]
            more = (
                f" (also differ: {', '.join(k for k, _, _ in diffs[1:4])}" if len(diffs) > 1 else ""
            )
            if more:
                more += ", ...)" if len(diffs) > 4 else ")"
            raise CheckpointError(
                f"checkpoint {where} was trained with {key}={saved!r} but the config says "
                f"{wanted!r}{more}"
            )
    return data


_DICT_ENTRIES = ("models", "optimizers", "counters", "rng", "heads_spec", "learner", "stats")
"""Conventional entries that, where present, are dicts (``models``' and ``optimizers``' values
too: state dicts); :func:`load_checkpoint` refuses another type in one line."""


def kind_of(x: Any) -> str:
    """A value's kind in a refusal: ``a list``, ``a tensor of shape [3, 3]``..."""
    if isinstance(x, torch.Tensor):
        return f"a tensor of shape {list(x.shape)}"
    name = type(x).__name__
    return f"an {name}" if name[:1] in "aeiou" else f"a {name}"


def _check_entry_types(data: Mapping[str, Any], where: str) -> None:
    """One line naming a conventional entry of the wrong type (``models=[1]``): what every
    command reads before it builds anything from the bundle."""
    for key in _DICT_ENTRIES:
        if key in data and not isinstance(data[key], Mapping):
            raise CheckpointError(
                f"checkpoint {where} is corrupt: {key} is {kind_of(data[key])}, expected a dict"
            )
    for group in ("models", "optimizers"):
        for name, sd in data.get(group, {}).items():
            if not isinstance(sd, Mapping):
                raise CheckpointError(
                    f"checkpoint {where} is corrupt: {group}[{name!r}] is {kind_of(sd)}, expected a "
                    "state dict"
                )


def is_training_checkpoint(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a taskvar checkpoint holding optimiser state (what a resume needs,
    unlike an exported ``heads.pt``); read memory-mapped, so a large replay costs nothing."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # not a (readable) torch file
        return False
    return isinstance(data, dict) and data.get("format") == FORMAT and bool(data.get("optimizers"))


RESUME_ENTRIES = ("models", "optimizers", "counters", "rng", "learner", "first_visit", "stats")
"""Bundle entries a training checkpoint needs to be resumed (``replay`` aside: the trainer names
a bundle written without it); ``env`` and ``carrier`` may be ``None`` (multi-process collection)
but must be present."""


def require_entries(
    bundle: Mapping[str, Any],
    path: str | os.PathLike,
    entries: Sequence[str] = (*RESUME_ENTRIES, "env", "carrier"),
    purpose: str = "resumed",
) -> None:
    """:class:`CheckpointError` (one line) naming the ``entries`` missing from ``bundle``: a
    damaged or hand-edited file, or a bundle of another kind (``heads.pt`` cannot be resumed)."""
    missing = [k for k in entries if k not in bundle]
    if missing:
        raise CheckpointError(
            f"checkpoint {str(path)!r} cannot be {purpose}: it has no "
            f"{', '.join(map(repr, missing))} entr{'y' if len(missing) == 1 else 'ies'} (not a "
            "training checkpoint, or an edited one)"
        )


EVAL_HEADS = "eval_heads"
"""``models`` entry of a training checkpoint with ``train.eval_ema_tau``: the Polyak-averaged
heads that evaluation reads (:func:`evaluation_heads_key`); ``"heads"`` holds the online ones."""


def evaluation_heads_key(bundle: dict[str, Any]) -> str:
    """The ``models`` entry evaluation reads: :data:`EVAL_HEADS` where the bundle has one (a run
    with ``train.eval_ema_tau``), else ``"heads"``."""
    return EVAL_HEADS if EVAL_HEADS in bundle.get("models", {}) else "heads"


def require_finite_heads(bundle: dict[str, Any], path: str | os.PathLike) -> None:
    """:class:`CheckpointError` when a checkpoint's heads (and :data:`EVAL_HEADS`, where it has
    them) hold a NaN or infinite value."""
    models = bundle.get("models", {})
    if not isinstance(models, Mapping) or not all(isinstance(m, Mapping) for m in models.values()):
        raise CheckpointError(f"checkpoint {str(path)!r} is corrupt: models is not a dict of dicts")
    heads = dict(models.get("heads", {}))
    heads.update({f"{EVAL_HEADS}.{k}": v for k, v in models.get(EVAL_HEADS, {}).items()})
    bad = [
        k
        for k, v in heads.items()
        if isinstance(v, torch.Tensor)
        and v.is_floating_point()
        and not bool(torch.isfinite(v).all())
    ]
    if bad:
        raise CheckpointError(
            f"checkpoint {str(path)!r} has non-finite heads ({bad[0]}"
            f"{', ...' if len(bad) > 1 else ''}): its run diverged; use an earlier checkpoint"
        )
