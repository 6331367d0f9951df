"""The results folders ``taskvar report`` reads (docs/report.md): :func:`load_result` reads one,
:func:`collect` expands every ``DIR`` (or its ``seed<k>/`` folders) and groups the results by
experiment and config; a group under :data:`MIN_SEEDS` seeds is exploratory. Bad input is one
line (:class:`ReportError`).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

MIN_SEEDS = 5
"""Training seeds a group needs before it scores a claim; a group of fewer is exploratory:
tabled and labelled, no verdict."""
KINDS = ("windy-fig2", "wargus-fig4", "scale", "eval")
"""``metrics.json`` ``experiment`` values of the results folders it reads."""


class ReportError(ValueError):
    """Bad input to ``taskvar report``: one line, and nothing is written."""


@dataclass
class Result:
    """One results folder: its kind, ``metrics.json``, config (seed removed) and training seeds."""

    path: Path
    kind: str
    metrics: dict[str, Any]
    config: dict[str, Any]
    seeds: tuple[int, ...]

    @property
    def commit(self) -> str | None:
        """The commit the results were computed at (``metrics.json``'s ``code.commit``,
        :func:`~taskvar_torch.experiments.results.code_version`); ``None`` where none is recorded."""
        code = self.metrics.get("code")
        commit = code.get("commit") if isinstance(code, dict) else None
        return str(commit) if commit else None

    @property
    def sealed(self) -> bool:
        """Whether its scores come from a sealed held-out split (``families.HELDOUT_SEED``): the
        Figure 2 and Figure 4 experiments' ``heldout`` scores, and a ``taskvar eval`` of a test
        distribution with a sealed seed (``metrics.json``'s ``sealed_seed``); not a family's other
        tests, nor an outside family's that has no sealed split."""
        if self.kind == "eval":
            return self.metrics.get("sealed_seed") is not None
        return self.kind in ("windy-fig2", "wargus-fig4")


@dataclass
class Group:
    """Results of one kind and one config: the unit a claim or a Results row is computed on."""

    kind: str
    config: dict[str, Any]
    results: list[Result] = field(default_factory=list)
    label: str = ""
    protocol: str = ""
    """Its label before a twin's distinguishing key was added: groups of one protocol share it
    (two realisations of Figure 4, one eager and one compiled)."""

    @property
    def seeds(self) -> list[int]:
        return [s for r in self.results for s in r.seeds]

    @property
    def commit(self) -> str | None:
        """The commit of its results (:attr:`Result.commit`; ``None``: none recorded), once
        :func:`check_commits` has found them one."""
        return self.results[0].commit if self.results else None

    @property
    def exploratory(self) -> bool:
        """Fewer than :data:`MIN_SEEDS` training seeds: tabled, labelled, and scoring no claim."""
        return len(self.seeds) < MIN_SEEDS

    @property
    def sealed(self) -> bool:
        """Every result of the group scored on a sealed held-out split (:attr:`Result.sealed`)."""
        return all(r.sealed for r in self.results)

    @property
    def digest(self) -> str:
        text = json.dumps(self.config, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:8]


# --------------------------------------------------------------------------------------------
# reading results folders


def read_json(path: Path) -> dict[str, Any]:
    """``path``'s JSON object; a one-line :class:`ReportError` when it cannot be read or is not
    an object."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ReportError(f"{path} cannot be read as JSON ({e})") from None
    if not isinstance(data, dict):
        raise ReportError(f"{path} is not a metrics.json (not an object)")
    return data


NOT_FINITE = "not a finite number: taskvar report aggregates finite results only; rerun it"
"""The end of the one-line refusal of a non-finite input."""
_NON_FINITE_TEXT = re.compile(r"(?i)(?<![\w.])[-+]?(?:nan|inf(?:inity)?)(?![\w.])")


def _json_path(prefix: str, key: Any) -> str:
    return f"{prefix}[{key}]" if isinstance(key, int) else (f"{prefix}.{key}" if prefix else key)


def check_finite_json(path: Path, data: Any, where: str = "") -> None:
    """A one-line :class:`ReportError` naming ``path`` and the key (``points[0].methods.x``) of
    the first ``NaN`` or infinite number in ``data`` (a ``metrics.json`` read with Python's
    ``json``, which accepts ``NaN`` and ``Infinity``; the library writes ``null`` instead)."""
    if isinstance(data, float) and not math.isfinite(data):
        raise ReportError(f"{path}: {where or 'the file'} is {data!r}, {NOT_FINITE}")
    items = (
        data.items()
        if isinstance(data, dict)
        else enumerate(data)
        if isinstance(data, list)
        else ()
    )
    for k, v in items:
        if isinstance(v, (dict, list, float)):
            check_finite_json(path, v, _json_path(where, k))


def check_finite_csv(path: Path) -> None:
    """A one-line :class:`ReportError` naming ``path``, the row (its line in the file, the header
    line 1) and the column of the first cell that reads as a non-finite number (``nan``, ``inf``,
    ``-Infinity``...); a file without such text is not parsed."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise ReportError(f"{path} cannot be read ({e.strerror})") from None
    if not _NON_FINITE_TEXT.search(text):
        return
    reader = csv.reader(io.StringIO(text))
    header = next(reader, [])
    for line, row in enumerate(reader, start=2):
        for name, cell in zip(header, row):
            if _NON_FINITE_TEXT.fullmatch(cell.strip()):
                raise ReportError(
                    f"{path}: row {line}, column {name!r} is {cell.strip()!r}, {NOT_FINITE}"
                )


def check_finite_inputs(folder: Path, metrics: dict[str, Any]) -> None:
    """Every number ``taskvar report`` may aggregate from a results folder is finite: its
    ``metrics.json`` (:func:`check_finite_json`) and the CSV files beside it (``episodes.csv``,
    ``per_trial*.csv``, :func:`check_finite_csv`); else one line naming the file, row and column
    (docs/report.md)."""
    check_finite_json(folder / "metrics.json", metrics)
    for path in sorted({*folder.glob("episodes.csv"), *folder.glob("per_trial*.csv")}):
        check_finite_csv(path)


def _config_yaml(folder: Path) -> dict[str, Any]:
    path = folder / "config.yaml"
    try:
        cfg = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ReportError(
            f"{folder} has no readable config.yaml ({e.__class__.__name__})"
        ) from None
    if not isinstance(cfg, dict):
        raise ReportError(f"{path} is not a config")
    return cfg


def _bundle_config(folder: Path, metrics: dict[str, Any]) -> dict[str, Any]:
    """The evaluated bundle's config (``taskvar eval``'s ``checkpoint``, as given or relative to
    the results folder)."""
    from taskvar_torch.checkpoint import CheckpointError, load_checkpoint

    ckpt = Path(str(metrics.get("checkpoint", "")))
    for path in (ckpt, folder / ckpt):
        if path.is_file():
            try:
                return dict(load_checkpoint(path)["config"])
            except CheckpointError as e:
                raise ReportError(f"{folder}: {e}") from None
    raise ReportError(
        f"{folder}: the bundle it evaluated ({str(ckpt)!r}) is not there, so its training seed "
        "and config are unknown"
    )


def load_result(folder: str | os.PathLike) -> Result:
    """One results folder (``folder/metrics.json`` of a :data:`KINDS` kind)."""
    folder = Path(folder)
    metrics = read_json(folder / "metrics.json")
    check_finite_inputs(folder, metrics)
    kind = metrics.get("experiment")
    if kind not in KINDS:
        raise ReportError(
            f"{folder} is not a results folder of {', '.join(KINDS)} (metrics.json 'experiment' "
            f"is {kind!r})"
        )
    if kind == "eval":
        cfg = _bundle_config(folder, metrics)
        seeds: tuple[int, ...] = (int(cfg.get("seed", 0)),)
        keep = ("family", "test", "shifts", "methods", "episodes")
        config = {"bundle": cfg, "eval": {k: metrics.get(k) for k in keep}}
    else:
        config = _config_yaml(folder)
        if kind == "wargus-fig4":  # one repetition per training seed
            seeds = tuple(int(s) for s in metrics.get("protocol", {}).get("seeds", ()))
            config.setdefault("experiment", {}).pop("runs", None)
        elif kind == "scale" and int(metrics.get("seeds", 1)) > 1:  # seeds=k: k seeds a cell
            seeds = tuple(int(config.get("seed", 0)) + k for k in range(int(metrics["seeds"])))
            config.pop("seeds", None)
        else:
            seeds = (int(config.get("seed", 0)),)
    config.pop("seed", None)
    if kind == "eval":
        config["bundle"].pop("seed", None)
    return Result(folder, kind, metrics, config, seeds)


_SEED_DIR = re.compile(r"seed(\d+)$")


def _expand(arg: str) -> list[Result]:
    """``arg``'s results: the folder itself, or its ``seed<k>/`` results folders."""
    folder = Path(arg)
    if not folder.is_dir():
        raise ReportError(f"{arg} is not a folder")
    if (folder / "metrics.json").is_file():
        return [load_result(folder)]
    seeds = sorted(
        (p for p in folder.iterdir() if p.is_dir() and _SEED_DIR.match(p.name)),
        key=lambda p: int(_SEED_DIR.match(p.name).group(1)),  # type: ignore[union-attr]
    )
    if not seeds:
        raise ReportError(
            f"{arg} is not a results folder: no metrics.json, nor seed<k>/metrics.json, of "
            "taskvar experiment or taskvar eval"
        )
    for p in seeds:
        if not (p / "metrics.json").is_file():
            raise ReportError(f"{p} has no metrics.json: not a results folder")
    return [load_result(p) for p in seeds]


def _difference(a: Any, b: Any, prefix: str = "") -> tuple[str, Any, Any]:
    """The first dotted key where two config dicts differ, and its two values."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if a.get(k) != b.get(k):
                return _difference(a.get(k), b.get(k), f"{prefix}{k}.")
    return prefix.rstrip("."), a, b


def _first_difference(a: Any, b: Any) -> str:
    """The first dotted key where two config dicts differ (for the one-line error)."""
    key, va, vb = _difference(a, b)
    return f"{key} ({va!r} vs {vb!r})"


def collect(dirs: Sequence[str]) -> list[Group]:
    """Every ``DIR``'s results, grouped by kind and config; the checks of the module docstring."""
    if not dirs:
        raise ReportError("give at least one results folder")
    groups: list[Group] = []
    for arg in dirs:
        results = _expand(arg)
        first = results[0]
        for r in results[1:]:  # one DIR is one claim: one kind, one config
            if r.kind != first.kind:
                raise ReportError(
                    f"{arg} mixes {first.kind} ({first.path}) and {r.kind} ({r.path}) results"
                )
            if r.config != first.config:
                raise ReportError(
                    f"{arg} mixes results of different configs as one claim: {first.path} and "
                    f"{r.path} differ in {_first_difference(first.config, r.config)}"
                )
        for g in groups:
            if g.kind == first.kind and g.config == first.config:
                g.results += results
                break
        else:
            groups.append(Group(first.kind, first.config, list(results)))
    for g in groups:
        where: dict[int, Path] = {}
        for r in g.results:
            for s in r.seeds:
                if s in where:
                    raise ReportError(
                        f"training seed {s} appears twice in one {g.kind} group ({where[s]}, "
                        f"{r.path})"
                    )
                where[s] = r.path
        g.label = g.protocol = _label(g)
    labels = []
    for g in groups:  # a label two groups share: the key that tells two apart, else the digest
        twins = [h for h in groups if h is not g and h.label == g.label]
        label = g.label
        if len(twins) == 1:
            key, value, _ = _difference(g.config, twins[0].config)
            value = str(value).lower() if isinstance(value, bool) else value  # as an override
            label = f"{g.label} ({key.removeprefix('bundle.')}={value})"
        elif twins:
            label = f"{g.label} (config {g.digest})"
        labels.append(label)
    for g, label in zip(groups, labels):
        g.label = label
    return groups


def exploratory_note(seeds: int) -> str:
    """How an exploratory group (fewer than :data:`MIN_SEEDS` training seeds) is labelled."""
    return f"exploratory: {seeds} seed{'s' if seeds != 1 else ''}, no claims"


def commit_text(commit: str | None) -> str:
    """A commit as a table or an error names it: its first 7 characters (``-dirty`` kept), or
    ``no recorded commit``."""
    if not commit:
        return "no recorded commit"
    return commit[:7] + ("-dirty" if commit.endswith("-dirty") else "")


def check_commits(sources: Sequence[tuple[str | None, str]], mixed: bool = False) -> None:
    """Refuse results of different commits (docs/report.md: one commit per table) in one line
    naming both, unless ``mixed`` (``taskvar report --mixed-commits``). ``sources``: ``(commit,
    where)`` pairs (``None``: none recorded, which differs from any recorded one; results that
    all record none pass)."""
    if mixed or not sources:
        return
    first, where = sources[0]
    for commit, other in sources[1:]:
        if commit != first:
            raise ReportError(
                f"results of different commits: {commit_text(first)} ({where}) and "
                f"{commit_text(commit)} ({other}); rerun them at one commit, or pass "
                "--mixed-commits to report them together"
            )


def _layout(env: dict, family: str | None) -> object:
    """A config's layout: in the family's own env section (``env.windy.layout``), or at ``env.*``
    where an older version wrote it."""
    own = env.get(family) if family else None
    return own.get("layout") if isinstance(own, dict) and "layout" in own else env.get("layout")


def _label(g: Group) -> str:
    c = g.config
    if g.kind == "windy-fig2":
        return f"windy-fig2, layout {_layout(c.get('env', {}), 'windy')}"
    if g.kind == "wargus-fig4":
        size = c.get("env", {}).get("wargus", {}).get("size")
        return f"wargus-fig4, {size}x{size}, {c.get('experiment', {}).get('trials')} trials"
    if g.kind == "scale":
        return f"scale, {', '.join(c.get('only') or ['every case'])}"
    e = c["eval"]
    shifts = f" --shift {' '.join(e['shifts'])}" if e.get("shifts") else ""
    family = e.get("family")
    env = c.get("bundle", {}).get("env", {})
    own = env.get(family)  # the family's own env section
    if isinstance(own, dict) and own.get("size") is not None:  # its grid, as Figure 4's label
        family = f"{family} {own['size']}x{own['size']}"
    layout = _layout(
        env, e.get("family")
    )  # a named layout other than the default, as windy-fig2's label
    if isinstance(layout, str) and layout != "default" and "\n" not in layout:
        family = f"{family} {layout}"
    return f"eval {family} --test {e.get('test')}{shifts}"


__all__ = [
    "KINDS",
    "NOT_FINITE",
    "check_finite_csv",
    "check_finite_inputs",
    "check_finite_json",
    "check_commits",
    "commit_text",
    "exploratory_note",
    "MIN_SEEDS",
    "Group",
    "ReportError",
    "Result",
    "collect",
    "load_result",
    "read_json",
]
