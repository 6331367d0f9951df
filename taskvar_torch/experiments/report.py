"""``taskvar report``: the paper's claims and the README's Results table, regenerated from results
folders by one command (issue 33; docs/claims.md is its output, docs/report.md its guide).

It reads results folders -- ``taskvar experiment windy-fig2`` / ``wargus-fig4`` / ``scale`` and
``taskvar eval --out`` folders, each holding ``metrics.json``, or a folder of ``seed<k>/`` results
folders (one training seed each) -- groups them by experiment and config (the config without its
seed), and for every group aggregates over training seeds with ``rliable``
(:mod:`taskvar_torch.experiments.aggregate`: IQM and mean with stratified-bootstrap 95% CIs,
paired differences, probability of improvement over the averaging policy, performance profiles).
The claims are scored on the **sealed held-out** instances (``families.HELDOUT_SEED``), never on
the nominal ones the designs were iterated on:

- **Figure 2** (§3.3.1): "offline interruption no worse than the averaging policy in almost 80% of
  episodes" -- the paired fraction no worse on held-out episodes (``metrics.json`` ``heldout``);
- **Figure 4, ordering** (§3.5.3): hierarchy > interruption > options > averaging over the first
  half of the trials -- paired per-repetition differences of held-out items per episode;
- **Figure 4, speed**: the hierarchy reaches 90% of its maximum in ~100 trials, averaging in
  > 350 -- each repetition's own held-out curve;
- **§3.2's premise**: a capability is less affected by variability than the full task -- over the
  points of a ``taskvar eval --test heldout --shift KEY=V1,V2,...`` curve, the range of the
  options controller's mean return (composed capabilities) against the averaging policy's (the
  full task), paired per seed.

Each claim gets the paper's figure, ours with its CI, and a verdict (``reproduced``, ``partly``,
``not``, or ``not measured`` where no results were given) by the rules in :data:`RULES`.
Results that score no claim (other families' evaluations, the baselines) can also join the README's
table alone (:func:`add_rows`, ``taskvar report --add``), the other rows kept.

The README's Results block is read in a minute (issue 48,
:mod:`~taskvar_torch.experiments.report_results`): the regret figure, per family one compact table
(methods as columns, a row per group, mean [95% CI] over seeds, the winners bold), and the table of
every result folded away; the per-group summaries behind them are kept beside the claims page
(``<stem>-results.json``) so that ``--add`` draws them again with the groups it adds.

Bad input is one line (:class:`ReportError`, a ``ValueError``) and nothing is written: a folder
that is not a results folder, results of different configs under one ``DIR`` (one claim), a
training seed twice, fewer than :data:`MIN_SEEDS` seeds, results without held-out scores, a
README without the marker comments, an output file (page, PNG, results JSON) that ``taskvar report``
did not write (unless ``overwrite``). Every file is written atomically (``taskvar_torch/io.py``).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from taskvar_torch.config.choices import FIG4_BASELINES
from taskvar_torch.experiments import aggregate
from taskvar_torch.experiments import report_results as at_a_glance
from taskvar_torch.experiments.curves import trials_to_fraction_of_max
from taskvar_torch.io import atomic_write
from taskvar_torch.run_folder import check_out_path, folder_lock

MIN_SEEDS = 5
"""Training seeds a group needs before it is quoted (issue 33: every headline over >= 5)."""
KINDS = ("windy-fig2", "wargus-fig4", "scale", "eval")
"""``metrics.json`` ``experiment`` values of the results folders it reads."""
README_START = "<!-- report:results:start -->"
README_END = "<!-- report:results:end -->"
GENERATED = "<!-- written by taskvar report: rerun it rather than editing this page -->"
"""First line of the claims page; a file without it is not replaced (unless ``overwrite``)."""
PNG_SOFTWARE = "taskvar report"
"""The PNG's ``Software`` text: a profile PNG without it is not replaced."""
NO_WORSE = 0.75
"""Figure 2: the least fraction no worse that reads as the paper's "almost 80%"."""
SPEED_RATIO = 2.0
"""Figure 4: the least averaging / hierarchy ratio of trials to 90% of maximum that reads as the
paper's ~100 vs > 350 (3.5x)."""
RULES = {
    "fig2": f"reproduced: the CI of the held-out fraction no worse lies at or above "
    f"{NO_WORSE:.0%} and interruption is better in some episodes (CI above 0); partly: at or above "
    f"{NO_WORSE:.0%} without being better anywhere (a tie, not a gain), or a CI across "
    f"{NO_WORSE:.0%}; not: the CI below {NO_WORSE:.0%}",
    "fig4_order": "reproduced: each of hierarchy - interruption, interruption - options, options - "
    "averaging has a paired CI above 0; partly: hierarchy - averaging above 0 but not the whole "
    "chain; not: otherwise",
    "fig4_speed": "reproduced: averaging - hierarchy in trials to 90% of maximum has a paired CI "
    f"above 0 and the means' ratio is at least {SPEED_RATIO:g}; partly: the CI above 0 with a "
    "smaller ratio; not: otherwise",
    "premise": "reproduced: averaging's range minus the options controller's range over the shift "
    "curve has a paired CI above 0 and the options controller is not worse than averaging over the "
    "curve (paired mean difference CI reaching 0 or above; a policy that fails everywhere is "
    "unaffected, not robust); partly: the smaller range without that, or a range CI across 0; "
    "not: a range CI at or below 0",
}
"""How each verdict is decided (printed on the claims page). Every CI is the mean's 95%
stratified-bootstrap CI over training seeds."""
CLAIMS = {
    "fig2": (
        "Figure 2: offline interruption no worse than the averaging policy (§3.3.1)",
        "no worse in almost 80% of episodes",
    ),
    "fig4_order": (
        "Figure 4: hierarchy > interruption > options > averaging, first half (§3.5.3)",
        "the hierarchy leads, then interruption, options, averaging",
    ),
    "fig4_speed": (
        "Figure 4: trials to 90% of maximum, hierarchy vs averaging (§3.5.3)",
        "~100 vs > 350 of 500 trials",
    ),
    "premise": (
        "§3.2: a capability is less affected by variability than the full task",
        "argued (shown through Figure 4's head start)",
    ),
}
"""Claim id -> (title, the paper's figure)."""
PAPER_METHODS = ("averaging", "options", "interruption", "hierarchy")


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


@dataclass
class Group:
    """Results of one kind and one config: the unit a claim or a README row is computed on."""

    kind: str
    config: dict[str, Any]
    results: list[Result] = field(default_factory=list)
    label: str = ""

    @property
    def seeds(self) -> list[int]:
        return [s for r in self.results for s in r.seeds]

    @property
    def digest(self) -> str:
        text = json.dumps(self.config, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:8]


@dataclass
class Claim:
    """One claim's row: the paper's figure, ours, the verdict and why, and detail lines."""

    key: str
    group: str
    ours: str
    verdict: str
    reason: str
    details: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# reading results folders


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ReportError(f"{path} cannot be read as JSON ({e})") from None
    if not isinstance(data, dict):
        raise ReportError(f"{path} is not a metrics.json (not an object)")
    return data


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
    metrics = _read_json(folder / "metrics.json")
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
        g.label = _label(g)
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
    for g in groups:
        if len(g.seeds) < MIN_SEEDS:
            raise ReportError(
                f"{g.label}: {len(g.seeds)} training seed(s) ({', '.join(str(r.path) for r in g.results)}); "
                f"a claim needs >= {MIN_SEEDS}"
            )
    return groups


def _label(g: Group) -> str:
    c = g.config
    if g.kind == "windy-fig2":
        return f"windy-fig2, layout {c.get('env', {}).get('layout')}"
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
    layout = env.get("layout")  # a named layout other than the default, as windy-fig2's label
    if isinstance(layout, str) and layout != "default" and "\n" not in layout:
        family = f"{family} {layout}"
    return f"eval {family} --test {e.get('test')}{shifts}"


# --------------------------------------------------------------------------------------------
# statistics per group


def _num(x: Any) -> float:
    return float("nan") if x is None else float(x)


def _ci(e: dict[str, Any], fmt: str = ".3f", which: str = "mean") -> str:
    lo, hi = e[f"{which}_ci95"]
    return f"{e[which]:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def _both(e: dict[str, Any], fmt: str = ".3f") -> str:
    return f"IQM {_ci(e, fmt, 'iqm')}, mean {_ci(e, fmt)}"


def _held(r: Result) -> dict[str, Any]:
    h = r.metrics.get("heldout")
    if not h:
        raise ReportError(
            f"{r.path}: {r.kind} results without held-out scores (run before the held-out split, "
            "issue 33); rerun the experiment"
        )
    return h


def _fig2(g: Group, reps: int) -> tuple[Claim, str, dict[str, Any]]:
    held = [_held(r) for r in g.results]
    per_seed = {
        "no worse": [_num(h["fraction_no_worse"]) for h in held],
        "better": [_num(h["fraction_better"]) for h in held],
        "null no worse": [_num(h["fraction_no_worse_null"]) for h in held],
        "interruption - averaging": [_num(h["mean_difference"]) for h in held],
    }
    est = aggregate.interval_estimates(per_seed, reps)
    returns = {
        m: [_num(h["mean_return"][m]["mean"]) for h in held]
        for m in ("averaging", "options", "interruption")
    }
    poi = aggregate.probability_of_improvement(returns, "averaging", reps)
    nw, better, null = est["no worse"], est["better"], est["null no worse"]
    lo, hi = nw["mean_ci95"]
    acts = better["mean_ci95"][0] > 0
    pct = lambda e: _ci(e, ".1%")  # noqa: E731
    if lo >= NO_WORSE and acts:
        verdict, why = "reproduced", f"no worse in {pct(nw)}, better in {pct(better)}"
    elif hi < NO_WORSE:
        verdict, why = "not", f"no worse in only {pct(nw)}"
    elif lo >= NO_WORSE:
        verdict = "partly"
        why = (
            f"no worse in {pct(nw)} but better in {pct(better)}: interruption ties the "
            "averaging policy rather than improving on it"
        )
    else:
        verdict, why = "partly", f"no worse in {pct(nw)}: the CI crosses {NO_WORSE:.0%}"
    if nw["mean"] <= null["mean"]:
        why += f"; the null (averaging against itself, other gusts) is already {pct(null)}"
    ours = f"no worse in {pct(nw)} of held-out episodes ({len(g.seeds)} seeds)"
    details = [
        f"fraction no worse (paired, sampled): {_both(nw, '.3f')}",
        f"fraction better: {_both(better, '.3f')}; null fraction no worse: {_both(null, '.3f')}",
        "interruption - averaging per episode, paired: " + _both(est["interruption - averaging"]),
        "P(improvement over averaging): "
        + ", ".join(f"{m} {v['probability']:.2f} {_pair(v['ci95'])}" for m, v in poi.items()),
    ]
    claim = Claim("fig2", g.label, ours, verdict, why, details)
    headline = (
        f"interruption no worse than averaging in {pct(nw)} of held-out episodes, better in "
        f"{pct(better)} (null {pct(null)}); interruption - averaging "
        f"{_ci(est['interruption - averaging'], '+.3f')} per episode"
    )
    return claim, headline, returns


def _pair(ci: Sequence[float]) -> str:
    return f"[{ci[0]:.2f}, {ci[1]:.2f}]"


def _fig4(g: Group, reps: int) -> tuple[list[Claim], str, dict[str, Any]]:
    held = [_held(r) for r in g.results]
    extra = [m for m in FIG4_BASELINES if all(m in h["methods"] for h in held)]
    curves = {
        m: np.concatenate([np.asarray(h["methods"][m]["curve_per_rep"], dtype=float) for h in held])
        for m in (*PAPER_METHODS, *extra)
    }  # (R, T) items per held-out test episode; experiment.baselines' curves in the evidence
    T = curves["averaging"].shape[1]
    half = max(T // 2, 1)
    first = {m: c[:, :half].mean(1) for m, c in curves.items()}
    links = [("hierarchy", "interruption"), ("interruption", "options"), ("options", "averaging")]
    diffs = aggregate.paired_differences(first, [*links, ("hierarchy", "averaging")], reps)
    level = aggregate.interval_estimates(first, reps)
    poi = aggregate.probability_of_improvement(first, "averaging", reps)

    def status(e: dict[str, Any]) -> str:
        lo, hi = e["mean_ci95"]
        if lo > 0:
            return "ahead"
        if hi < 0:
            return "behind"
        return "tied" if lo == hi == 0 else "level"

    sts = [status(diffs[f"{a} - {b}"]) for a, b in links]
    overall = diffs["hierarchy - averaging"]
    if all(s == "ahead" for s in sts):
        verdict = "reproduced"
    elif status(overall) == "ahead":
        verdict = "partly"
    else:
        verdict = "not"
    why = "; ".join(f"{a} vs {b}: {s}" for (a, b), s in zip(links, sts))
    order = Claim(
        "fig4_order",
        g.label,
        f"hierarchy - averaging {_ci(overall, '+.3f')} items per held-out episode, trials 1-{half} "
        f"({len(g.seeds)} seeds)",
        verdict,
        why,
        [
            f"items per held-out episode, trials 1-{half}: "
            + "; ".join(f"{m} {_both(level[m])}" for m in curves),
            "paired differences: " + "; ".join(f"{k} {_ci(v, '+.3f')}" for k, v in diffs.items()),
            "P(improvement over averaging): "
            + ", ".join(f"{m} {v['probability']:.2f} {_pair(v['ci95'])}" for m, v in poi.items()),
        ],
    )
    t90 = {
        m: np.array([trials_to_fraction_of_max(c) for c in curves[m]], dtype=float)
        for m in ("hierarchy", "averaging")
    }
    speed = aggregate.interval_estimates(t90, reps)
    gap = aggregate.paired_differences(t90, [("averaging", "hierarchy")], reps)[
        "averaging - hierarchy"
    ]
    ratio = speed["averaging"]["mean"] / max(speed["hierarchy"]["mean"], 1e-9)
    if gap["mean_ci95"][0] > 0 and ratio >= SPEED_RATIO:
        sv = "reproduced"
    elif gap["mean_ci95"][0] > 0:
        sv = "partly"
    else:
        sv = "not"
    speed_claim = Claim(
        "fig4_speed",
        g.label,
        f"hierarchy {_ci(speed['hierarchy'], '.0f')} vs averaging "
        f"{_ci(speed['averaging'], '.0f')} of {T} trials ({len(g.seeds)} seeds)",
        sv,
        f"averaging - hierarchy {_ci(gap, '+.0f')} trials, paired; ratio {ratio:.1f}"
        + ("" if T == 500 else f" (the paper's protocol has 500 trials, these {T})"),
        [
            f"trials to 90% of maximum (each repetition's held-out curve): {_both(speed['hierarchy'], '.0f')} (hierarchy), {_both(speed['averaging'], '.0f')} (averaging)"
        ],
    )
    headline = (
        f"items per held-out episode, trials 1-{half}: "
        + ", ".join(f"{m} {_ci(level[m], '.2f')}" for m in PAPER_METHODS)
        + f"; 90% of maximum in {speed['hierarchy']['mean']:.0f} vs "
        f"{speed['averaging']['mean']:.0f} trials (hierarchy vs averaging)"
    )
    profile = {m: c[:, :half] for m, c in curves.items()}
    return [order, speed_claim], headline, profile


def _eval(g: Group, reps: int) -> tuple[Claim | None, str, dict[str, Any]]:
    methods = list(g.config["eval"]["methods"] or [])
    points = [r.metrics["points"] for r in g.results]
    scores = {
        m: np.array([[_num(p["methods"][m]["mean_return"]) for p in pts] for pts in points])
        for m in methods
    }  # (seeds, points)
    est = aggregate.interval_estimates(scores, reps)
    test = g.config["eval"]["test"]
    where = "held-out" if test == "heldout" else f"--test {test}"
    headline = f"IQM mean return ({where}, {scores[methods[0]].shape[1]} point(s)): " + ", ".join(
        f"{m} {_ci(est[m], '.3f', 'iqm')}" for m in methods
    )
    claim = None
    if (
        test == "heldout"
        and scores[methods[0]].shape[1] >= 2
        and {"averaging", "options"} <= set(methods)
    ):
        spread = {m: scores[m].max(1) - scores[m].min(1) for m in ("averaging", "options")}
        d = aggregate.paired_differences(spread, [("averaging", "options")], reps)[
            "averaging - options"
        ]
        lo, hi = d["mean_ci95"]
        level = {m: scores[m].mean(1) for m in ("averaging", "options")}
        worse = aggregate.paired_differences(level, [("options", "averaging")], reps)[
            "options - averaging"
        ]
        fails = worse["mean_ci95"][1] < 0  # options clearly worse over the whole curve
        verdict = "not" if hi <= 0 else ("reproduced" if lo > 0 and not fails else "partly")
        rng = aggregate.interval_estimates(spread, reps)
        claim = Claim(
            "premise",
            g.label,
            f"range of mean return over the curve: options {_ci(rng['options'])} vs averaging "
            f"{_ci(rng['averaging'])} ({len(g.seeds)} seeds)",
            verdict,
            f"averaging - options range {_ci(d, '+.3f')}, paired"
            + (
                f"; but options are worse over the curve ({_ci(worse, '+.3f')} per episode): "
                "unaffected because they fail everywhere"
                if fails and lo > 0
                else ""
            )
            + "; the options controller composes the capabilities, so this tests them composed",
            [f"mean return per point and seed: {headline}"],
        )
    return claim, headline, scores


def _scale_seeds(metrics: dict[str, Any]) -> list[dict[str, dict[str, float]]]:
    """One ``{cell: {method: score}}`` per training seed of a scale folder (``per_seed`` where the
    experiment ran ``seeds > 1``, else the cell's own methods); the score is the gap closed on
    windy cells, the mean return elsewhere."""
    n = max(len(c.get("per_seed") or [None]) for c in metrics.get("cells", [])) or 1
    out: list[dict[str, dict[str, float]]] = [{} for _ in range(n)]
    for c in metrics.get("cells", []):
        runs = [ps["methods"] for ps in c["per_seed"]] if c.get("per_seed") else [c["methods"]]
        for k, methods in enumerate(runs):
            for m, v in (methods or {}).items():
                if v:
                    score = (
                        v.get("gap_closed") if c.get("family") == "windy" else v.get("mean_return")
                    )
                    out[k].setdefault(f"{c['case']}-n{c['num_envs']}", {})[m] = _num(score)
    return out


def _scale(g: Group, reps: int) -> str:
    seeds = [row for r in g.results for row in _scale_seeds(r.metrics)]
    windy = sorted({cell for row in seeds for cell in row if cell.startswith("windy")})
    methods = [m for m in PAPER_METHODS if all(m in row.get(c, {}) for row in seeds for c in windy)]
    parts = []
    for m in methods if windy else []:
        mat = np.array([[row[c][m] for c in windy] for row in seeds])  # (seeds, cells)
        e = aggregate.interval_estimates({m: mat}, reps)[m]
        parts.append(f"{m} {_ci(e, '.2f', 'iqm')}")
    return "gap to the exact optimum closed, windy cells (IQM over seeds x cells): " + (
        ", ".join(parts) or "no windy cells"
    )


# --------------------------------------------------------------------------------------------
# the report


@dataclass
class Report:
    """What ``taskvar report`` writes: the claims, the README rows, the profile panels and the
    per-group summaries behind the compact tables and the regret figure
    (:mod:`~taskvar_torch.experiments.report_results`)."""

    groups: list[Group]
    claims: list[Claim]
    rows: list[tuple[str, str, int, str]]  # (label, headline, seeds, config digest)
    profiles: list[tuple[str, dict[str, Any], str]]  # (title, scores, x label)
    reps: int
    summaries: list[dict[str, Any]] = field(default_factory=list)


def build_report(dirs: Sequence[str], reps: int = aggregate.REPS) -> Report:
    """Read and check every ``DIR`` (:func:`collect`), then compute every group's figures."""
    groups = collect(dirs)
    claims: list[Claim] = []
    rows: list[tuple[str, str, int, str]] = []
    profiles: list[tuple[str, dict[str, Any], str]] = []
    summaries: list[dict[str, Any]] = []
    for g in groups:
        if g.kind == "windy-fig2":
            claim, headline, returns = _fig2(g, reps)
            claims.append(claim)
            profiles.append((g.label, returns, "mean held-out return per seed"))
            summaries.append(_fig2_summary(g, returns, reps))
        elif g.kind == "wargus-fig4":
            fig4_claims, headline, curves = _fig4(g, reps)
            claims += fig4_claims
            profiles.append((g.label, curves, "held-out items per episode, first half"))
            summaries.append(_fig4_summary(g, curves, reps))
        elif g.kind == "eval":
            claim, headline, scores = _eval(g, reps)
            if claim is not None:
                claims.append(claim)
            profiles.append((g.label, scores, "mean return per seed and point"))
            summaries.append(_eval_summary(g, scores, reps))
        else:  # the scale experiment's gap closed: its row of the table of every result only
            headline = _scale(g, reps)
        rows.append((g.label, headline, len(g.seeds), g.digest))
    return Report(groups, claims, rows, profiles, reps, summaries)


# --------------------------------------------------------------------------------------------
# the compact tables' and the regret figure's data, per group (experiments/report_results.py)


def _group_info(g: Group, family: Any, row: str, budget: str, score: str) -> dict[str, Any]:
    return {
        "label": g.label,
        "digest": g.digest,
        "kind": g.kind,
        "family": str(family),
        "row": row,
        "budget": budget,
        "seeds": len(g.seeds),
        "score": score,
    }


def _frames(train: Any) -> str:
    frames = train.get("total_frames") if isinstance(train, dict) else None
    return "-" if frames is None else at_a_glance.frames_text(frames)


def _with_ceiling(per_seed: dict[str, np.ndarray]) -> tuple[str, Any, set[str]] | None:
    """The regret to the ``informed`` head where it was evaluated (the results' learnt ceiling),
    from sampled returns."""
    if at_a_glance.CEILING not in per_seed:
        return None
    reference, arrays = at_a_glance.regret_to_ceiling(per_seed)
    return reference, arrays, set(arrays)


def _fig2_summary(g: Group, returns: dict[str, Any], reps: int) -> dict[str, Any]:
    per_seed = {m: np.asarray(v, dtype=np.float64) for m, v in returns.items()}
    row = "Figure 2 protocol, " + g.label.removeprefix("windy-fig2, ")
    info = _group_info(
        g,
        g.config.get("family") or g.kind,
        row,
        _frames(g.config.get("train")),
        "mean return per held-out episode",
    )
    return at_a_glance.summarise(info, per_seed, _with_ceiling(per_seed), reps)


def _fig4_summary(g: Group, curves: dict[str, Any], reps: int) -> dict[str, Any]:
    per_seed = {m: np.asarray(c, dtype=np.float64).mean(1) for m, c in curves.items()}
    half = np.asarray(next(iter(curves.values()))).shape[1]
    row = f"Figure 4 {g.label.removeprefix('wargus-fig4, ')}: trials 1-{half}"
    trials = g.config.get("experiment", {}).get("trials")
    info = _group_info(
        g,
        g.config.get("family") or g.kind,
        row,
        f"{trials} trials",
        "Figure 4: items per held-out episode over the first half of the trials",
    )
    return at_a_glance.summarise(info, per_seed, _with_ceiling(per_seed), reps)


def _eval_summary(g: Group, scores: dict[str, np.ndarray], reps: int) -> dict[str, Any]:
    family = g.config["eval"]["family"]
    per_seed = {m: s.mean(1) for m, s in scores.items()}  # the points' mean, per seed
    n = next(iter(scores.values())).shape[1]
    info = _group_info(
        g,
        family,
        at_a_glance.row_name(g.label, family),
        _frames(g.config.get("bundle", {}).get("train")),
        "mean return per episode" + (f" (mean over a curve's {n} points)" if n > 1 else ""),
    )
    points = [r.metrics["points"] for r in g.results]
    rows = [p["methods"][m] for pts in points for p in pts for m in scores]
    regret = None
    if all("regret_mean" in r for r in rows):  # the exact per-instance optimum, every point
        arrays = {
            m: np.array(
                [np.mean([_num(p["methods"][m]["regret_mean"]) for p in pts]) for pts in points]
            )
            for m in scores
        }
        sampled = {
            m
            for m in scores
            if any(p["methods"][m].get("regret_sampled") for pts in points for p in pts)
        }
        regret = (at_a_glance.EXACT, arrays, sampled)
    else:
        regret = _with_ceiling(per_seed)
    return at_a_glance.summarise(info, per_seed, regret, reps)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def claims_markdown(
    report: Report,
    png_name: str | None,
    dirs: Sequence[str],
    results_png: str | None = None,
    self_link: str = "claims.md",
) -> str:
    """The claims page; ``results_png``: the regret figure beside it, shown with the table of
    every result (``self_link``: the page's own file name, where that table's rows link)."""
    lines = [
        GENERATED,
        "# The paper's claims against ours",
        "",
        f"Written by `taskvar report {' '.join(dirs)}`. Every figure is over training seeds "
        f"(>= {MIN_SEEDS}), on the sealed held-out instances (`families.HELDOUT_SEED`: no design "
        "choice was made on them), aggregated with rliable: interquartile mean (IQM) and mean "
        f"with stratified-bootstrap 95% CIs ({report.reps} resamples, seeded), paired per seed "
        "where the methods played the same episodes; probability of improvement over the "
        "averaging policy as rliable defines it (unpaired).",
        "",
        "| claim | paper | results | ours (mean [95% CI]) | verdict | why |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for key, (title, paper) in CLAIMS.items():
        got = [c for c in report.claims if c.key == key]
        if not got:
            lines.append(f"| {title} | {paper} | none given | - | not measured | no results |")
        for c in got:
            lines.append(
                f"| {_cell(title)} | {_cell(paper)} | {_cell(c.group)} | {_cell(c.ours)} | "
                f"**{c.verdict}** | {_cell(c.reason)} |"
            )
    lines += ["", "## How the verdicts are decided", ""]
    lines += [f"- {CLAIMS[k][0]}: {v}." for k, v in RULES.items()]
    lines += ["", "## Details", ""]
    for c in report.claims:
        lines.append(f"**{CLAIMS[c.key][0]}, {c.group}**")
        lines.append("")
        lines += [f"- {d}" for d in c.details]
        lines.append("")
    lines += ["## Results read", "", "| results | kind | training seeds | config | folders |"]
    lines.append("| --- | --- | --- | --- | --- |")
    for g in report.groups:
        folders = ", ".join(f"`{r.path}`" for r in g.results)
        lines.append(
            f"| {_cell(g.label)} | {g.kind} | {', '.join(map(str, g.seeds))} | {g.digest} | "
            f"{folders} |"
        )
    if png_name:
        lines += ["", f"![performance profiles]({png_name})", ""]
        lines.append(
            "Performance profiles (rliable's score distributions): the fraction of each method's "
            "scores above tau, with 95% bootstrap bands."
        )
    lines += ["", "## Every result", "", results_table(report, self_link)]
    if results_png:
        lines += ["", f"![regret per method and family]({results_png})", ""]
        lines.append(at_a_glance.FIGURE_CAPTION)
    return "\n".join(lines) + "\n"


SHORT = {"fig2": "Fig. 2", "fig4_order": "order", "fig4_speed": "speed", "premise": "§3.2"}


def results_table(report: Report, claims_link: str = "docs/claims.md") -> str:
    """The README's Results table (between :data:`README_START` and :data:`README_END`);
    ``claims_link``: the claims page, relative to the README."""
    lines = [
        "| experiment | headline (IQM or mean [95% CI] over seeds; held-out instances unless the "
        "row names another --test) | training seeds | config | claims |",
        "| --- | --- | --- | --- | --- |",
    ]
    for label, headline, n, digest in report.rows:
        verdicts = ", ".join(
            f"{SHORT[c.key]} {c.verdict}" for c in report.claims if c.group == label
        )
        lines.append(
            f"| {_cell(label)} | {_cell(headline)} | {n} | {digest} | "
            f"{verdicts or '-'} ([claims]({claims_link})) |"
        )
    return "\n".join(lines)


def replace_block(text: str, block: str, where: str) -> str:
    """``text`` with what lies between the marker comments replaced by ``block``."""
    if text.count(README_START) != 1 or text.count(README_END) != 1:
        raise ReportError(
            f"{where} must hold {README_START} and {README_END} once each (the Results table "
            "goes between them)"
        )
    a = text.index(README_START) + len(README_START)
    b = text.index(README_END)
    if b < a:
        raise ReportError(f"{where}: {README_END} comes before {README_START}")
    return text[:a] + "\n" + block + "\n" + text[b:]


def _read_readme(readme: str | os.PathLike) -> str:
    """The README's text, checked for the Results markers before anything is computed."""
    try:
        text = Path(readme).read_text(encoding="utf-8")
    except OSError as e:
        raise ReportError(f"--readme {str(readme)!r} cannot be read ({e.strerror})") from None
    replace_block(text, "", str(readme))
    return text


def _row_key(line: str) -> tuple[str, str] | None:
    """A Results row's (experiment label, config digest): the cells a row is known by."""
    cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())]
    if len(cells) < 6 or cells[1] in ("experiment", "---"):
        return None
    return cells[1], cells[4]


def merge_rows(block: str, table: str) -> str:
    """``table``'s rows merged into the Results table ``block``: a row of the same experiment
    and config replaces the old one where it stands, new ones go last, the others are kept."""
    new = {_row_key(line): line for line in table.splitlines()[2:]}
    head = table.splitlines()[:2]
    kept = []
    for line in block.strip().splitlines():
        key = _row_key(line)
        if key is None:
            continue
        kept.append(new.pop(key, line))
    return "\n".join(head + kept + list(new.values()))


def results_files(claims: str | os.PathLike) -> tuple[Path, Path]:
    """Beside the claims page ``claims``: the regret figure ``img/<stem>-results.png`` and the
    summaries behind it and the compact tables, ``<stem>-results.json``."""
    claims = Path(claims)
    return claims.parent / "img" / f"{claims.stem}-results.png", claims.with_name(
        f"{claims.stem}-results.json"
    )


def _read_summaries(path: Path) -> list[dict[str, Any]]:
    """The summaries ``taskvar report`` kept in ``path`` (none where there is no file)."""
    if not path.exists():
        return []
    data = _read_json(path)
    if data.get("written_by") != PNG_SOFTWARE:
        raise ReportError(f"{str(path)!r} exists and was not written by taskvar report; move it")
    return list(data.get("groups", []))


def _summaries_json(summaries: Sequence[dict[str, Any]]) -> bytes:
    data = {"written_by": PNG_SOFTWARE, "groups": list(summaries)}
    return (json.dumps(data, indent=1) + "\n").encode()


def _results_block(
    summaries: Sequence[dict[str, Any]], details: str, png: Path | None, readme: str | os.PathLike
) -> str:
    """The README's Results block: the figure (linked from the README), the compact tables, the
    table of every result ``details`` folded away, and a note on rows without a summary."""
    known = {(s["label"], s["digest"]) for s in summaries}
    keys = [_row_key(line) for line in details.splitlines()]
    missing = sum(1 for k in keys if k is not None and k not in known)
    figure = None if png is None else Path(os.path.relpath(png, Path(readme).parent)).as_posix()
    return at_a_glance.results_block(summaries, details, figure, missing)


def add_rows(
    dirs: Sequence[str],
    readme: str | os.PathLike,
    claims: str | os.PathLike | None = None,
    reps: int = aggregate.REPS,
) -> tuple[list[Path], Report]:
    """``taskvar report --add``: add these folders' rows to the README's Results, keeping the
    rows of results not given (each row names its config digest), and write no claims page.
    Their summaries join those kept beside the claims page (``<stem>-results.json``; a group of
    the same label and config replaced), and the compact tables and the regret figure are drawn
    again from them all. Refused where a folder scores one of the paper's claims: the claims
    page must then be rewritten from every folder. ``claims``: the claims page the rows link to
    (default ``docs/claims.md`` beside the README)."""
    if int(reps) < 100:
        raise ReportError(f"--reps must be >= 100 bootstrap resamples, got {reps}")
    _refuse_inside_results(dirs, readme, "--readme")
    text = _read_readme(readme)
    claims_path = Path(readme).parent / "docs" / "claims.md" if claims is None else Path(claims)
    png, data = results_files(claims_path)
    kept = _read_summaries(data)
    if png.exists() and not _ours_png(png):
        raise ReportError(
            f"{str(png)!r} exists and was not written by taskvar report; move it or rerun without "
            "--add and with --overwrite"
        )
    report = build_report(dirs, reps)
    if report.claims:
        scored = sorted({c.group for c in report.claims})
        raise ReportError(
            f"--add: {'; '.join(scored)} score the paper's claims; rerun taskvar report with "
            "every results folder and --out docs/claims.md instead"
        )
    a = text.index(README_START) + len(README_START)
    old = text[a : text.index(README_END)]
    link = Path(os.path.relpath(claims_path, Path(readme).parent)).as_posix()
    details = merge_rows(at_a_glance.details_of(old), results_table(report, link))
    new = {(s["label"], s["digest"]): s for s in report.summaries}
    summaries = [new.pop((s["label"], s["digest"]), s) for s in kept] + list(new.values())
    image = at_a_glance.results_png(summaries, PNG_SOFTWARE)
    block = _results_block(summaries, details, png if image is not None else None, readme)
    new_text = replace_block(text, block, str(readme)).encode()
    written = []
    data_bytes = _summaries_json(summaries)
    with folder_lock(Path(readme).resolve().parent, "--readme"):
        if image is not None:
            written.append(atomic_write(png, lambda f: f.write(image)))
        written.append(atomic_write(data, lambda f: f.write(data_bytes)))
        written.append(atomic_write(Path(readme), lambda f: f.write(new_text)))
    return written, report


def profile_png(report: Report, reps: int) -> bytes | None:
    """The performance profiles, one panel per group with methods, as PNG bytes."""
    panels = [p for p in report.profiles if p[1]]
    if not panels:
        return None
    from taskvar_torch.experiments.plots import _pyplot

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 3.6), squeeze=False)
    for ax, (title, scores, xlabel) in zip(axes[0], panels):
        allv = np.concatenate([np.asarray(v, dtype=float).ravel() for v in scores.values()])
        allv = allv[np.isfinite(allv)]
        lo, hi = (float(allv.min()), float(allv.max())) if allv.size else (0.0, 1.0)
        taus = np.linspace(lo, hi if hi > lo else lo + 1.0, 41)
        prof, cis = aggregate.performance_profile(scores, taus, reps=min(reps, 1000))
        aggregate.plot_performance_profiles(ax, prof, cis, taus, xlabel)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": PNG_SOFTWARE})
    plt.close(fig)
    return buf.getvalue()


def _ours_md(path: Path) -> bool:
    try:
        with path.open(encoding="utf-8") as f:
            return f.readline().rstrip("\n") == GENERATED
    except (OSError, UnicodeDecodeError):
        return False


def _ours_png(path: Path) -> bool:
    try:
        from PIL import Image

        with Image.open(path) as im:
            return im.info.get("Software") == PNG_SOFTWARE
    except Exception:  # not an image, unreadable: not ours
        return False


def write_report(
    dirs: Sequence[str],
    out: str | os.PathLike,
    readme: str | os.PathLike | None = None,
    reps: int = aggregate.REPS,
    overwrite: bool = False,
) -> tuple[list[Path], Report]:
    """``taskvar report``: check everything, compute everything, then write the regret figure
    and the summaries behind it and the compact tables (:func:`results_files`), the claims page
    ``out``, its profile PNG (``img/<out stem>-profile.png`` beside it) and, with ``readme``, the
    README's Results block. Returns the files written and the report."""
    out = check_out_path(out)
    _refuse_inside_results(dirs, out, "--out")
    if readme is not None:
        _refuse_inside_results(dirs, readme, "--readme")
    png = out.parent / "img" / f"{out.stem}-profile.png"
    results_png, data = results_files(out)
    if int(reps) < 100:
        raise ReportError(f"--reps must be >= 100 bootstrap resamples, got {reps}")
    if out.exists() and not overwrite and not _ours_md(out):
        raise ReportError(
            f"--out {str(out)!r} exists and was not written by taskvar report; choose another "
            "--out or pass --overwrite"
        )
    for path in (png, results_png):
        if path.exists() and not overwrite and not _ours_png(path):
            raise ReportError(
                f"{str(path)!r} exists and was not written by taskvar report; move it or pass "
                "--overwrite"
            )
    if not overwrite:
        _read_summaries(data)  # refused where it is someone else's
    readme_text = None if readme is None else _read_readme(readme)
    report = build_report(dirs, reps)
    image = profile_png(report, reps)
    results_image = at_a_glance.results_png(report.summaries, PNG_SOFTWARE)
    rel = os.path.relpath(png, out.parent) if image is not None else None
    results_rel = (
        Path(os.path.relpath(results_png, out.parent)).as_posix()
        if results_image is not None
        else None
    )
    page = claims_markdown(report, rel, dirs, results_rel, out.name).encode()
    new_readme = None
    if readme_text is not None:
        details = results_table(report, Path(os.path.relpath(out, Path(readme).parent)).as_posix())
        block = _results_block(
            report.summaries, details, results_png if results_image is not None else None, readme
        )
        new_readme = replace_block(readme_text, block, str(readme)).encode()
    data_bytes = _summaries_json(report.summaries)
    written = []
    out.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(out.parent):  # one taskvar command writing in the folder at a time
        if image is not None:
            written.append(atomic_write(png, lambda f: f.write(image)))
        if results_image is not None:
            written.append(atomic_write(results_png, lambda f: f.write(results_image)))
        written.append(atomic_write(data, lambda f: f.write(data_bytes)))
        written.append(atomic_write(out, lambda f: f.write(page)))
        if new_readme is not None:
            written.append(atomic_write(Path(readme), lambda f: f.write(new_readme)))
    return written, report


def _refuse_inside_results(dirs: Sequence[str], path: str | os.PathLike, flag: str) -> None:
    """A one-line :class:`ReportError` when ``path`` (a file the report writes) lies in one of
    the results folders ``dirs`` it reads."""
    target = Path(path).resolve()
    for d in dirs:
        if Path(d).resolve() in target.parents:
            raise ReportError(
                f"{flag} {str(path)!r} lies in the results folder {d!r} that taskvar report reads; "
                f"choose another {flag}"
            )


__all__ = [
    "CLAIMS",
    "GENERATED",
    "KINDS",
    "MIN_SEEDS",
    "PNG_SOFTWARE",
    "README_END",
    "README_START",
    "RULES",
    "Claim",
    "Group",
    "Report",
    "ReportError",
    "Result",
    "add_rows",
    "build_report",
    "claims_markdown",
    "collect",
    "load_result",
    "merge_rows",
    "replace_block",
    "results_files",
    "results_table",
    "write_report",
]
