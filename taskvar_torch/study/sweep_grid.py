"""The grid of a sweep (docs/sweeps.md): points from ``key=v1,v2,...`` (:func:`expand_points`),
their configs (:func:`load_point_configs`), the points already complete (:func:`completed_points`)
and the summary (:func:`headline`, :func:`format_summary`).
"""

from __future__ import annotations

import itertools
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from taskvar_torch.config import Config, config_to_dict, load_config


@dataclass(frozen=True)
class SweepPoint:
    """One point: its folder name, its swept values and every override it applies (in order)."""

    name: str
    values: dict[str, str]
    overrides: tuple[str, ...]


# --------------------------------------------------------------------------------------------
# points


def split_values(text: str) -> list[str]:
    """``'0,1'`` -> ``['0', '1']``; commas inside ``[...]``, ``{...}`` or quotes do not split."""
    parts, depth, quote, start = [], 0, "", 0
    for i, c in enumerate(text):
        if quote:
            quote = "" if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c in "[{":
            depth += 1
        elif c in "]}":
            depth -= 1
        elif c == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return [p.strip() for p in parts]


def point_name(values: dict[str, str]) -> str:
    """Folder name of a point: ``key=value`` pairs joined by ``,``, other characters as ``_``."""
    if not values:
        return "run"
    text = ",".join(f"{k}={v}" for k, v in values.items())
    return re.sub(r"[^A-Za-z0-9._=,+-]", "_", text)


def expand_points(items: Sequence[str]) -> list[SweepPoint]:
    """The Cartesian product of the swept keys (``key=v1,v2``), fixed overrides (``key=v``) first.

    Raises:
        ValueError: an item without ``=``, an empty value, or a key given twice.
    """
    fixed: list[str] = []
    swept: dict[str, list[str]] = {}
    seen: set[str] = set()
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"sweep override {item!r} must look like key.sub=v1,v2,... ")
        if key in seen:
            raise ValueError(f"sweep key {key!r} is given twice; give its values once: {key}=v1,v2")
        seen.add(key)
        values = split_values(text)
        if any(v == "" for v in values):
            raise ValueError(
                f"sweep key {key!r} has an empty value in {text!r}; give {key}=v1,v2,... "
                "with non-empty values"
            )
        if len(values) == 1:
            fixed.append(f"{key}={values[0]}")
        else:
            swept[key] = values
    points, names = [], set()
    for combo in itertools.product(*swept.values()):
        values = dict(zip(swept, combo))
        name = point_name(values)
        if name in names:  # two values that differ only in unsafe characters
            name = f"{name},{len(points)}"
        names.add(name)
        points.append(SweepPoint(name, values, (*fixed, *(f"{k}={v}" for k, v in values.items()))))
    return points


def load_point_configs(
    config: str | os.PathLike, points: Sequence[SweepPoint], quick: bool = False
) -> list[Config]:
    """Every point's config, strictly loaded (the config loader's one-line errors, before any run)."""
    cfgs = []
    for p in points:
        try:
            cfgs.append(load_config(config, p.overrides, quick=quick))
        except ValueError as e:
            raise ValueError(f"{e} [sweep point {p.name}]" if p.values else str(e)) from None
    return cfgs


def headline(metrics: dict[str, Any]) -> dict[str, Any]:
    """The summary-table numbers of one point's ``metrics.json`` (Figure 2: fractions no worse and
    mean difference; Figure 4: final scores and trials to 90%).
    """
    if metrics.get("experiment") == "windy-fig2":
        keys = (
            "fraction_no_worse",
            "mean_difference",
            "fraction_no_worse_null",
            "fraction_no_worse_exact",
        )
        row = {k: metrics.get(k) for k in keys}
        south = metrics.get("south_only") or {}
        row.update({f"south_only.{k}": south.get(k) for k in keys})
        return row
    row = {f"final_score.{n}": m["final_score"] for n, m in metrics["methods"].items()}
    row.update(
        {f"trials_to_90pct.{n}": m["trials_to_90pct"] for n, m in metrics["methods"].items()}
    )
    return row


def completed_points(
    out: Path, points: Sequence[SweepPoint], cfgs: Sequence[Config]
) -> dict[int, dict[str, Any]]:
    """The points already complete in ``out`` (``metrics.json`` present and ``config.yaml`` equal to
    the point's): ``{index: {"metrics", "seconds"}}``.

    Raises:
        ValueError: a point folder holds results of another config, or unreadable files.
    """
    done: dict[int, dict[str, Any]] = {}
    for i, (p, cfg) in enumerate(zip(points, cfgs)):
        folder = out / p.name
        if not (folder / "metrics.json").is_file():
            continue
        try:
            saved = OmegaConf.to_container(OmegaConf.load(folder / "config.yaml"))
            metrics = json.loads((folder / "metrics.json").read_text())
        except Exception as e:  # a missing or damaged file: not this sweep's complete point
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ValueError(
                f"--resume: point folder {str(folder)!r} holds metrics.json but its config.yaml "
                f"or metrics.json cannot be read ({first}); remove the folder or use --overwrite"
            ) from None
        wanted = config_to_dict(cfg)
        if saved != wanted:
            key = _first_difference(saved, wanted)
            raise ValueError(
                f"--resume: point folder {str(folder)!r} holds results of another config "
                f"({key} differs); this is not the same sweep: use --overwrite or another --out"
            )
        seconds = metrics.get("wall_seconds", (metrics.get("timing") or {}).get("wall_seconds"))
        done[i] = {"metrics": metrics, "seconds": seconds}
    return done


def _first_difference(a: Any, b: Any, prefix: str = "") -> str:
    """The first dotted key whose value differs between two nested dicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in list(a) + [k for k in b if k not in a]:
            if a.get(k, "<absent>") != b.get(k, "<absent>"):
                return _first_difference(a.get(k), b.get(k), f"{prefix}{k}.")
    return prefix.rstrip(".") or "config"


def summary_rows(points: Sequence[Any], results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One summary row per point: its swept values, headline numbers, seconds (and error)."""
    rows = []
    for p, r in zip(points, results):
        row: dict[str, Any] = {"point": p.name, **p.values}
        row.update(headline(r["metrics"]) if "metrics" in r else {})
        row["seconds"] = r["seconds"]
        if any("error" in x for x in results):
            row["error"] = r.get("error", "")
        rows.append(row)
    return rows


def format_summary(rows: Sequence[dict[str, Any]], fields: Sequence[str]) -> str:
    """Aligned text table of the summary rows (floats to 3 decimals)."""

    def cell(v: Any) -> str:
        return f"{v:.3f}" if isinstance(v, float) else ("" if v is None else str(v))

    table = [list(fields)] + [[cell(r.get(f)) for f in fields] for r in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(fields))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(line, widths)).rstrip() for line in table)


__all__ = [
    "SweepPoint",
    "completed_points",
    "expand_points",
    "format_summary",
    "headline",
    "load_point_configs",
    "point_name",
    "split_values",
    "summary_rows",
]
