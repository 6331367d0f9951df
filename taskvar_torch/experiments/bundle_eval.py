"""``taskvar eval``: every method of a trained bundle, side by side, on test distributions and
shifts of any family, with the bundle's controller settings or others (docs/evaluation.md).

:func:`eval_bundle` builds each method's controller with the bundle's settings (thresholds
calibrated on the *training* distribution) and plays the same paired episodes with every method;
each test point gives mean return with a 95% CI, interruptions and the control split and, where the
family has an oracle, exact returns and regret against the per-instance optimum.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from taskvar_torch import keys
from taskvar_torch.config.controller import check_controller_overrides, controller_settings
from taskvar_torch.config.memory import check_memory
from taskvar_torch.config.memory import estimate as estimate_memory
from taskvar_torch.contract import family
from taskvar_torch.experiments.baselines import (
    available_baselines,
    load_baselines,
)
from taskvar_torch.experiments.evaluation import mean_ci95
from taskvar_torch.experiments.paired import (
    affordable,
    check_baseline_fits,
    check_fits,
    episode_seed,
    exact_regret,
    parse_methods,
    play,
    point_oracle,
)
from taskvar_torch.experiments.plots import pyplot, save_figure
from taskvar_torch.experiments.regret_plots import PNG_NAME as REGRET_PNG
from taskvar_torch.experiments.regret_plots import plot_regret, regret_by_instance
from taskvar_torch.experiments.regret_steps import PNG_NAME as STEPS_PNG
from taskvar_torch.experiments.regret_steps import (
    episode_step_regret,
    plot_regret_by_step,
    regret_by_step,
    step_regret_affordable,
    supports_step_regret,
)
from taskvar_torch.experiments.results import code_version, write_csv, write_json
from taskvar_torch.experiments.shift import EvalPoint, Shift, parse_shift, shift_points
from taskvar_torch.factory import (
    calibrate,
    load_heads,
    make_env,
    make_method_controller,
    make_subtasks,
    training_states,
)
from taskvar_torch.oracle.episodes import optimal_episode_returns
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import ResultsFolder, refuse_inside

METRICS_NAME = "metrics.json"
CSV_NAME = "episodes.csv"
PNG_NAME = "eval.png"


def summarise(r: dict[str, np.ndarray], names: Sequence[str], method: str) -> dict[str, Any]:
    """Mean return with its 95% CI, mean length, interruptions and control split of one method."""
    mean, ci = mean_ci95(torch.as_tensor(r["return"], dtype=torch.float64))
    out: dict[str, Any] = {
        "mean_return": float(np.mean(r["return"], dtype=np.float64)),
        "mean_return_ci95": ci,
        "mean_length": float(np.mean(r["length"], dtype=np.float64)),
    }
    if method != "averaging":
        out["interruptions_per_episode"] = float(np.mean(r["interruptions"], dtype=np.float64))
        steps = np.array([r[f"steps_{o}"].sum() for o in range(len(names))], dtype=np.float64)
        total = steps.sum()
        out["control"] = {n: float(s / total) if total else 0.0 for n, s in zip(names, steps)}
    return out


def eval_bundle(
    checkpoint: str | os.PathLike,
    method: str = "all",
    test: str | None = None,
    shifts: Sequence[str | Shift] = (),
    episodes: int = 1000,
    seed: int | None = None,
    noise_seed: int | None = None,
    batch_size: int | None = None,
    out_dir: str | os.PathLike | None = None,
    progress: bool = True,
    plots: bool = True,
    overwrite: bool = False,
    exact: bool | None = None,
    by_frames: bool = False,
    controller: Sequence[str] = (),
) -> dict[str, Any]:
    """Evaluate the bundle at ``checkpoint`` with ``method`` (``all``, one, or a comma list) on test
    distribution ``test`` (``None``: the family's first) with ``shifts``; no retraining.

    ``seed`` defaults to the bundle's ``seed + 1``. Writes ``metrics.json``, ``episodes.csv`` and
    ``eval.png`` into ``out_dir`` when given (a staged
    :class:`~taskvar_torch.run_folder.ResultsFolder`; ``overwrite``); returns the metrics.
    ``exact``: exact returns and regret always (``True``), never (``False``) or where cheap
    (``None``, else noted in ``exact_skipped``). ``by_frames``: also ``regret_by_frames`` over the
    run's heads snapshots. ``controller``: controller settings changed from the bundle's
    (docs/controllers.md), recorded in ``controller_overrides``.
    """
    controller = check_controller_overrides(controller)  # one-line errors before any loading
    if out_dir is None:
        return _evaluate(
            checkpoint, method, test, shifts, episodes, seed, noise_seed, batch_size, None,
            progress, plots, exact, by_frames, controller,
        )  # fmt: skip
    folder = ResultsFolder(out_dir, overwrite, "taskvar eval")
    refuse_inside(checkpoint, folder.out, "--checkpoint")
    with folder as staging:  # locked; written in a staging folder, swapped in whole at the end
        return _evaluate(
            checkpoint, method, test, shifts, episodes, seed, noise_seed, batch_size, staging,
            progress, plots, exact, by_frames, controller,
        )  # fmt: skip


def _evaluate(
    checkpoint: str | os.PathLike,
    method: str,
    test: str | None,
    shifts: Sequence[str | Shift],
    episodes: int,
    seed: int | None,
    noise_seed: int | None,
    batch_size: int | None,
    out_dir: Path | None,
    progress: bool,
    plots: bool,
    exact: bool | None,
    by_frames: bool,
    controller: Sequence[str],
) -> dict[str, Any]:
    """:func:`eval_bundle` writing into ``out_dir`` (the staging folder) when given."""
    if int(episodes) < 1:
        raise ValueError(f"--episodes must be >= 1, got {episodes}")
    shifts = [s if isinstance(s, Shift) else parse_shift(s) for s in shifts]
    heads, cfg = load_heads(checkpoint, controller=controller)
    fam = family(cfg)
    if (exact or by_frames) and not fam.exact_oracle:  # what needs the per-instance optimum
        flag = "--by-frames (exact regret by training frames)" if by_frames else "--exact"
        raise ValueError(
            f"{flag} needs an exact oracle of the family, and family {fam.name!r} has none "
            "(Family.oracle, docs/families.md): drop it; sampled returns are reported without it"
        )
    points = shift_points(cfg, test, shifts)  # every input error before any episode is played
    test_name = test if test is not None else next(iter(fam.tests))
    train_subtasks = make_subtasks(cfg, make_env(cfg, 1))
    methods = parse_methods(
        method, train_subtasks, heads, available_baselines(checkpoint), checkpoint
    )
    baselines = load_baselines(checkpoint, methods, cfg)  # recurrent, informed (docs/memory.md)
    seed = episode_seed(cfg, test_name, seed)
    bs = int(batch_size or cfg.eval.batch_size)
    rows_kept = len(points) * len(methods) * int(episodes)  # one result row per episode
    batch = dataclasses.replace(cfg.eval, batch_size=min(bs, int(episodes)))  # --batch-size
    check_memory(
        estimate_memory(dataclasses.replace(cfg, eval=batch), training=False, episodes=rows_kept)
    )
    calibration = None  # the hierarchy's thresholds: on the bundle's *training* distribution
    if "hierarchy" in methods and cfg.train.robustness_threshold == "calibrated":
        calibration = calibrate(cfg, heads, train_subtasks, training_states(cfg, heads))
    point_subtasks = []
    for point in points:  # every point must fit the bundle before any episode is played
        probe = make_env(point.cfg, 1, instances=point.instances)
        point_subtasks.append(make_subtasks(point.cfg, probe))
        check_fits(point, heads, point_subtasks[-1], probe)
        for m in methods:
            if m in baselines:
                check_baseline_fits(point, baselines[m], probe)
    if by_frames:  # its one-line refusals before any episode is played
        from taskvar_torch.experiments.regret_frames import check_by_frames

        if exact is False:
            raise ValueError("--by-frames computes exact returns; drop --no-exact")
        check_by_frames(checkpoint, points)
    bar = progress_bar(
        total=len(points) * len(methods) * int(episodes), disable=not progress, desc="eval"
    )
    rows: list[dict[str, Any]] = []
    results = []
    by_step = None  # per-step regret (one test point, an oracle with step_regret)
    skipped: list[str] = []
    for point, subtasks in zip(points, point_subtasks):
        oracle = point_oracle(cfg, point) if exact is not False else None
        optimum, rows_have_optimum = None, False  # exact per-instance optimum per episode
        per_method = {}
        steps = len(points) == 1 and supports_step_regret(oracle)  # regret against the step
        step_gaps: dict[str, np.ndarray] = {}
        step_alive: dict[str, np.ndarray] = {}
        for m in methods:
            if m in baselines:
                ctrl = baselines[m]
            else:
                ctrl = make_method_controller(
                    point.cfg, m, heads, subtasks, calibration=calibration
                )
            traced_keys = (keys.CELL, keys.ACTION) if steps else ()
            r = play(ctrl, point, int(episodes), seed, bs, noise_seed, bar, steps=traced_keys)
            traced = [r.pop(k, None) for k in ("step_cell", "step_action", "step_alive")]
            per_method[m] = summarise(r, heads.option_names, "averaging" if m in baselines else m)
            instance = {k[len("instance_") :]: v for k, v in r.items() if k.startswith("instance_")}
            if oracle is not None and exact is None and not affordable(oracle, instance):
                skipped.append(point.label or test_name)
                oracle = None
            if oracle is not None and m in baselines:  # not memoryless: regret of the sample
                if optimum is None and hasattr(oracle, "optimal_return"):
                    optimum = optimal_episode_returns(oracle, instance, r["start"])
                if optimum is not None:
                    mean, ci = mean_ci95(
                        torch.as_tensor(optimum - r["return"], dtype=torch.float64)
                    )
                    per_method[m].update(
                        regret_mean=float(mean), regret_ci95=ci, regret_sampled=True
                    )
                    if not rows_have_optimum:
                        r["optimum_return"] = optimum
                        rows_have_optimum = True
            elif oracle is not None:
                exact_r, optimum, regret = exact_regret(
                    oracle, ctrl, point.cfg, instance, r["start"], optimum
                )
                per_method[m]["exact_mean_return"] = float(np.mean(exact_r, dtype=np.float64))
                r["exact_return"] = exact_r
                if regret is not None:
                    per_method[m].update(regret)
                    if not rows_have_optimum:
                        r["optimum_return"] = optimum  # once per episode (the first method)
                        rows_have_optimum = True
            if (
                steps
                and oracle is not None
                and not (exact or step_regret_affordable(oracle, instance))
            ):
                steps = False  # many distinct instances (Taxi's continuous ranges): --exact
            if steps and oracle is not None:  # V*(s_t) - Q*(s_t, a_t) in the episode's instance
                step_gaps[m] = episode_step_regret(oracle, instance, *traced)
                step_alive[m] = traced[2]
            rows += _csv_rows(point, m, r)
        results.append({"shift": point.label, "value": point.value, "methods": per_method})
        if optimum is not None:  # the ceiling: an agent that knows the instance
            results[-1]["optimum_mean_return"] = float(np.mean(optimum, dtype=np.float64))
        if step_gaps:
            by_step = regret_by_step(step_gaps, step_alive)
    bar.close()
    metrics = _metrics(checkpoint, cfg, test_name, shifts, methods, seed, noise_seed, episodes)
    metrics["points"] = results
    metrics["controller"] = controller_settings(cfg)  # the settings played (bundle's or changed)
    metrics["controller_overrides"] = list(controller)
    if skipped:
        metrics["exact_skipped"] = (
            f"exact returns not computed for {sorted(set(skipped))}: too many distinct instances "
            "for the oracle (taskvar eval --exact computes them anyway, slowly)"
        )
    if by_step is not None:
        metrics["regret_by_step"] = by_step
    if len(points) == 1 and len(methods) == 1:  # the keys of a one-method evaluation
        metrics.update({"method": methods[0], **results[0]["methods"][methods[0]]})
    if by_frames:  # the same paired episodes, on every heads snapshot of the run
        from taskvar_torch.experiments.regret_frames import regret_by_frames

        metrics["regret_by_frames"] = regret_by_frames(
            checkpoint,
            method,
            test_name,
            shifts,
            episodes,
            seed,
            noise_seed,
            bs,
            exact,
            out_dir=out_dir,
            plots=plots,
            controller=controller,
        )
    if baselines:  # each baseline's own training budget (it may differ from the heads')
        metrics["baseline_frames"] = {m: b.total_frames for m, b in baselines.items()}
        metrics["heads_frames"] = int(cfg.train.total_frames)
    if out_dir is not None:
        _write(Path(out_dir), metrics, rows, plots)
    return metrics


def _metrics(checkpoint, cfg, test, shifts, methods, seed, noise_seed, episodes) -> dict[str, Any]:
    out = {
        "experiment": "eval",
        "code": code_version(),
        "checkpoint": str(checkpoint),
        "family": cfg.family,
        "test": test,
        "test_description": family(cfg).tests[test].description,
        "shifts": [f"{s.key}={','.join(s.values)}" for s in shifts],
        "method": ",".join(methods),
        "methods": list(methods),
        "seed": seed,
        "noise_seed": 0 if noise_seed is None else int(noise_seed),
        "episodes": int(episodes),
    }
    sealed = family(cfg).tests[test].seed
    if sealed is not None:  # the held-out seed this bundle's own draw comes from (``seed``)
        out["sealed_seed"] = int(sealed)
    return out


CSV_FIELDS = ("shift", "method", "episode", "return", "length", "interruptions")


def _csv_rows(point: EvalPoint, method: str, r: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    extra = [
        k
        for k in r
        if k.startswith("instance_") or k in ("start", "exact_return", "optimum_return")
    ]
    return [
        {
            "shift": point.label,
            "method": method,
            "episode": i,
            "return": float(r["return"][i]),
            "length": int(r["length"][i]),
            "interruptions": int(r["interruptions"][i]),
            **{k: r[k][i].item() for k in extra},
        }
        for i in range(len(r["return"]))
    ]


def _write(out: Path, metrics: dict[str, Any], rows: list[dict[str, Any]], plots: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    fields = list(CSV_FIELDS) + sorted({k for r in rows for k in r} - set(CSV_FIELDS))
    write_csv(out / CSV_NAME, rows, fields)
    regret = None
    if len(metrics["points"]) == 1:  # where each method loses, by the hidden parameter
        regret = regret_by_instance(rows, metrics["methods"])
        if regret is not None:
            metrics["regret_by_instance"] = regret
    if plots:
        plot_eval(metrics, out / PNG_NAME)
        metrics["figures"] = [PNG_NAME]  # relative to the folder
        title = f"{metrics['family']}: test {metrics['test']}"
        if regret is not None:
            plot_regret(regret, out / REGRET_PNG, title)
            metrics["figures"].append(REGRET_PNG)
        if "regret_by_step" in metrics:
            plot_regret_by_step(metrics["regret_by_step"], out / STEPS_PNG, title)
            metrics["figures"].append(STEPS_PNG)
    write_json(out / METRICS_NAME, metrics)


def plot_eval(metrics: dict[str, Any], path: Path) -> Path:
    """Each method's mean return with its 95% CI: bars for one test point, else the shift curve
    against the swept value (with the oracle's exact values dashed where there are any)."""
    plt = pyplot()
    points, methods = metrics["points"], metrics["methods"]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    if len(points) == 1:
        ms = points[0]["methods"]
        ax.bar(
            methods,
            [ms[m]["mean_return"] for m in methods],
            yerr=[ms[m]["mean_return_ci95"] for m in methods],
            capsize=4,
            color="#4c72b0",
        )
        ax.set_ylabel("mean return (95% CI)")
        ax.set_title(f"{metrics['family']}: test {metrics['test']}")
    else:
        key = points[0]["shift"].split("=")[0]
        xs = np.arange(len(points))
        for m in methods:
            y = np.array([p["methods"][m]["mean_return"] for p in points])
            ci = np.array([p["methods"][m]["mean_return_ci95"] for p in points])
            (line,) = ax.plot(xs, y, marker="o", label=m)
            ax.fill_between(xs, y - ci, y + ci, alpha=0.2, color=line.get_color())
            if all("exact_mean_return" in p["methods"][m] for p in points):
                exact = [p["methods"][m]["exact_mean_return"] for p in points]
                ax.plot(xs, exact, ls="--", color=line.get_color(), label=f"{m} (exact)")
        ax.set_xticks(xs, [str(p["value"]) for p in points])
        ax.set_xlabel(key)
        ax.set_ylabel("mean return (95% CI band)")
        ax.set_title(f"{metrics['family']} shift curve: test {metrics['test']}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


def format_table(metrics: dict[str, Any]) -> str:
    """The methods side by side per test point: mean return +- 95% CI (exact where known, and
    the regret against the exact per-instance optimum +- its 95% CI), interruptions per episode
    and the control split."""
    lines = [
        f"{metrics['family']} bundle {metrics['checkpoint']}: test {metrics['test']} "
        f"({metrics['test_description']}), {metrics['episodes']} paired episodes, seed "
        f"{metrics['seed']}"
    ]
    fixed = [s for s in metrics["shifts"] if "," not in s]
    if fixed:
        lines.append(f"shifted: {', '.join(fixed)}")
    for p in metrics["points"]:
        if p["shift"]:
            lines.append(f"{p['shift']}:")
        lines.append(
            f"  {'method':<13} {'mean return':>12} {'+-95%':>8} {'exact':>9} {'regret':>16} "
            f"{'interr./ep':>10}  control"
        )
        for m, r in p["methods"].items():
            exact = f"{r['exact_mean_return']:9.3f}" if "exact_mean_return" in r else f"{'':>9}"
            regret = (
                f"{r['regret_mean']:8.3f} +-{r['regret_ci95']:5.3f}"
                if "regret_mean" in r
                else f"{'':>16}"
            )
            inter = r.get("interruptions_per_episode")
            inter_s = f"{inter:10.2f}" if inter is not None else f"{'':>10}"
            control = " ".join(f"{k} {v:.0%}" for k, v in r.get("control", {}).items())
            lines.append(
                f"  {m:<13} {r['mean_return']:12.3f} {r['mean_return_ci95']:8.3f} {exact} {regret} "
                f"{inter_s}  {control}"
            )
        if "optimum_mean_return" in p:
            lines.append(
                f"  {'optimum':<13} {'':>12} {'':>8} {p['optimum_mean_return']:9.3f} "
                f"{0.0:8.3f}{'':>8}   (exact per-instance optimum: knows the instance)"
            )
    sampled = sorted(
        {m for p in metrics["points"] for m, r in p["methods"].items() if r.get("regret_sampled")}
    )
    if sampled:
        lines.append(
            f"  ({', '.join(sampled)}: not memoryless, so no exact value; regret = exact optimum "
            "minus the sampled return of the same episode)"
        )
    heads = metrics.get("heads_frames")
    more = {m: f for m, f in (metrics.get("baseline_frames") or {}).items() if f and f != heads}
    if heads and more:  # a row of another budget is labelled, never read as equal (docs/memory.md)
        lines.append(
            f"  (trained on another budget than the heads' {heads:,} frames: "
            + ", ".join(f"{m} {f:,}" for m, f in sorted(more.items()))
            + ")"
        )
    if "exact_skipped" in metrics:
        lines.append(f"  ({metrics['exact_skipped']})")
    return "\n".join(lines)


__all__ = [
    "eval_bundle",
    "format_table",
    "plot_eval",
    "summarise",
]
