"""The reliability probe of issue 44 as a suite: inputs and faults an attacker or a careless user
would try, each asserting its outcome class.

Outcome classes: **refused** (exit status 2, exactly one stderr line ``taskvar COMMAND: error:
...`` naming what to change, no traceback, nothing written), **survived** (the command completes),
**interrupted** (status 128 + N and one line), and **files untouched** (every file of a folder
byte for byte as it was). Nothing ends in a signal, a traceback, a silently wrong result or a
lost file.

Sections: checkpoints (tampered entries, the fused Adam's unchecked shapes, a Hypothesis strategy
tampering with a real checkpoint), config (numbers out of range, allocations that cannot exist,
devices, seeds, threads), the CLI itself (plugins, bugs, memory), results folders (``--out ''``,
``--out .``, a source inside its destination, concurrent and killed commands, ``--overwrite``),
and Gymnasium seeding. Commands run in this process through :func:`taskvar_torch.cli.main`
unless the attack is a signal or a crash (then ``python -m taskvar_torch.cli``, ~4 s each).
"""

from __future__ import annotations

import copy
import hashlib
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import taskvar_torch  # noqa: F401  (registers the Gymnasium ids)
from taskvar_torch import cli
from taskvar_torch.checkpoint import load_checkpoint, save_checkpoint
from taskvar_torch.run_folder import LOCK_NAME, ResultsFolder, lock_folder, unlock_folder

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
C = str(ROOT / "configs" / "windy_corridor.yaml")  # the probe's C
T = ["train.total_frames=2048", "train.init_random_frames=512", "train.eps_decay_frames=1024"]
TINY = [  # a run of ~2 s with a periodic checkpoint, optimiser state and a replay buffer
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=300",
    "train.checkpoint_every=200",
    "train.log_every=300",
    "train.init_random_frames=100",
    "train.batch_size=16",
    "train.updates_per_batch=1",
    "train.buffer_size=1000",
]
EVAL = ["--episodes", "8", "--batch-size", "8", "--no-progress"]
GYM_IDS = ("taskvar/WindyGrid-v0", "taskvar/Wargus-v0", "taskvar/Taxi-v0")


# --------------------------------------------------------------------------------------------
# helpers: run a command, read its outcome, fingerprint a folder


def run(argv: list[str], capsys) -> tuple[int, list[str]]:
    """``taskvar ARGV`` in this process: ``(status, stderr lines)``."""
    try:
        status = cli.main(argv)
    except SystemExit as e:
        status = e.code
    err = capsys.readouterr().err
    return status, [line for line in err.splitlines() if line.strip()]


def refused(outcome: tuple[int, list[str]], command: str, *needles: str) -> str:
    """The outcome is one line ``taskvar COMMAND: error: ...`` with every needle, status 2."""
    status, lines = outcome
    assert status == 2, lines
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"taskvar {command}: error: "), lines[0]
    assert "Traceback" not in lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def fingerprint(folder: Path) -> dict[str, str]:
    """Every entry under ``folder`` (links not followed): a file's sha256, ``dir`` or the link."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        if p.is_symlink():
            out[rel] = f"-> {os.readlink(p)}"
        elif p.is_dir():
            out[rel] = "dir"
        else:
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def taskvar(*args: str, hook: str = "", timeout: int = 300) -> subprocess.CompletedProcess:
    """``taskvar ARGS`` in a new single-threaded process, after ``hook`` (Python) has run."""
    code = textwrap.dedent(hook) + "\nimport sys\nfrom taskvar_torch.cli import main\n"
    code += "sys.exit(main(sys.argv[1:]))\n"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-c", code, *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def one_line(stderr: str, *needles: str) -> str:
    lines = [x for x in stderr.splitlines() if x.strip()]
    assert len(lines) == 1, stderr[-3000:]
    assert "Traceback" not in stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A tiny trained run of the probe's config: ``checkpoint_000000200.pt``, ``final.pt``,
    ``heads.pt``, logs."""
    out = tmp_path_factory.mktemp("attacks") / "run"
    status = cli.main(["train", C, "--out", str(out), *TINY, "--no-progress"])
    assert status == 0
    return out


@pytest.fixture(scope="module")
def bundle(run_dir) -> dict[str, Any]:
    """``final.pt`` as plain data, without the keys :func:`save_checkpoint` adds."""
    data = load_checkpoint(run_dir / "final.pt")
    for k in ("format", "format_version", "versions"):
        data.pop(k)
    return data


def tampered(bundle: dict[str, Any], path: tuple, value: Any, where: Path) -> Path:
    """A copy of ``bundle`` with the entry at ``path`` set to ``value`` (``DELETE``: removed),
    saved at ``where``."""
    data = copy.deepcopy(bundle)
    node = data
    for k in path[:-1]:
        node = node[k]
    if value is DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return save_checkpoint(where, data)


DELETE = object()


# --------------------------------------------------------------------------------------------
# checkpoints: every entry checked before anything is built from it

HEAD = "heads.averaging.module.stack.weights.0"
RESUME_TAMPERING = {  # the probe's, then more of the same classes
    "adam exp_avg 3x3": (("optimizers", "adam", "state", 0, "exp_avg"), torch.zeros(3, 3)),
    "counters.frames lots": (("counters", "frames"), "lots"),
    "counters.frames negative": (("counters", "frames"), -100000),
    "counters.frames missing": (("counters", "frames"), DELETE),
    "rng.torch 3 bytes": (("rng", "torch"), torch.zeros(3, dtype=torch.uint8)),
    "rng without numpy": (("rng", "numpy"), DELETE),
    "replay width": (("replay", "data", "observation"), torch.zeros(1, 99)),
    "replay.size lying": (("replay", "size"), 10**6),
    "env.cell 10**6": (("env", "_extra_state", "cell"), torch.full((4,), 10**6)),
    "carrier shape": (("carrier", "observation"), torch.zeros(4, 99)),
    "first_visit shape": (("first_visit", "seen"), torch.zeros(2, 2, dtype=torch.bool)),
    "stats a string": (("stats",), "abc"),
    "config env.num_envs": (("config", "env", "num_envs"), 8),
    "models=[1]": (("models",), [1]),
    # more of the same classes
    "adam step a string": (("optimizers", "adam", "state", 0, "step"), "x"),
    "adam exp_avg_sq missing": (("optimizers", "adam", "state", 1, "exp_avg_sq"), DELETE),
    "adam state of no parameter": (("optimizers", "adam", "state", 99), {}),
    "adam lr nan": (("optimizers", "adam", "param_groups", 0, "lr"), float("nan")),
    "adam exp_avg float64": (("optimizers", "adam", "state", 0, "exp_avg"), None),  # set below
    "head tensor shape": (("models", "heads", HEAD), torch.zeros(1, 2, 3)),
    "target tensor missing": (("models", "targets", HEAD.removeprefix("heads.")), DELETE),
    "counters.updates a float": (("counters", "updates"), 1.5),
    "counters.batches a bool": (("counters", "batches"), True),
    "counters extra": (("counters", "epochs"), 3),
    "rng.python short": (("rng", "python", "state"), [1, 2, 3]),
    "rng.numpy pos 10**6": (("rng", "numpy", "pos"), 10**6),
    "replay generator 10 bytes": (
        ("rng", "generators", "replay"),
        torch.zeros(10, dtype=torch.uint8),
    ),
    "replay dtype": (("replay", "data", "action"), None),  # set below
    "replay writer cursor": (("replay", "writer", "_cursor"), 7),
    "learner num_updates -1": (("learner", "num_updates"), -1),
    "learner loss_sum a list": (("learner", "loss_sum"), [1]),
    "env dir 9": (("env", "_extra_state", "dir"), torch.full((4,), 9)),
    "env p nan": (("env", "_extra_state", "p"), torch.full((4,), float("nan"))),
    "env seed 2**40": (("env", "_extra_state", "seed"), 2**40),
    "stats tensor shape": (("stats", "episodes"), torch.zeros(3)),
    "carrier missing": (("carrier", "action"), DELETE),
}


def _value(bundle: dict[str, Any], name: str, value: Any) -> Any:
    if name == "adam exp_avg float64":
        return bundle["optimizers"]["adam"]["state"][0]["exp_avg"].double()
    if name == "replay dtype":
        return bundle["replay"]["data"]["action"].float()
    return value


PROBE_TAMPERING = list(RESUME_TAMPERING)[: list(RESUME_TAMPERING).index("adam step a string")]
"""The probe's own cases (make test-fast); the rest, more of the same classes, run in make test."""


@pytest.mark.parametrize(
    "name",
    [
        n if n in PROBE_TAMPERING else pytest.param(n, marks=pytest.mark.slow)
        for n in RESUME_TAMPERING
    ],
)
def test_a_tampered_entry_is_a_one_line_refusal_of_resume(name, bundle, tmp_path, capsys):
    path, value = RESUME_TAMPERING[name]
    ckpt = tampered(bundle, path, _value(bundle, name, value), tmp_path / "x.pt")
    out = tmp_path / "out"
    line = refused(run(["train", "--resume", str(ckpt), "--out", str(out)], capsys), "train")
    assert str(ckpt) in line
    assert not out.exists()  # refused before anything was written


def test_a_shape_mismatch_names_the_tensor_and_both_shapes(bundle, tmp_path, capsys):
    ckpt = tampered(bundle, ("models", "heads", HEAD), torch.zeros(1, 2, 3), tmp_path / "x.pt")
    want = list(bundle["models"]["heads"][HEAD].shape)
    line = refused(run(["eval", "--checkpoint", str(ckpt), *EVAL], capsys), "eval")
    assert f"models['heads']['{HEAD}'] has shape [1, 2, 3], expected {want}" in line
    line = refused(
        run(["train", "--resume", str(ckpt), "--out", str(tmp_path / "o")], capsys), "train"
    )
    assert f"has shape [1, 2, 3], expected {want}" in line


@pytest.mark.parametrize("command", ["eval", "export"])
def test_a_bundle_for_a_device_torch_cannot_use_is_refused(command, bundle, tmp_path, capsys):
    ckpt = tampered(bundle, ("config", "device"), "meta", tmp_path / "x.pt")
    argv = {
        "eval": ["eval", "--checkpoint", str(ckpt), *EVAL],
        "export": ["export", str(ckpt), "--out", str(tmp_path / "h.pt")],
    }[command]
    refused(run(argv, capsys), command, "device='meta' cannot run taskvar_torch")


@pytest.mark.slow  # a process of its own: ~5 s of imports
def test_the_fused_adam_is_never_given_state_of_the_wrong_shape(bundle, tmp_path):
    """The probe's heap corruption (SIGABRT / SIGSEGV): a ``weights_only``-clean checkpoint whose
    Adam moments have another shape. In a process of its own: a crash cannot take pytest."""
    path = ("optimizers", "adam", "state", 0, "exp_avg")
    ckpt = tampered(bundle, path, torch.zeros(3, 3), tmp_path / "x.pt")
    r = taskvar("train", "--resume", str(ckpt), "--out", str(tmp_path / "o"), "--no-progress")
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])  # not -6 / -11
    one_line(r.stderr, "optimizers['adam']['state'][0]['exp_avg'] has shape [3, 3], expected")


@pytest.mark.parametrize("command", ["eval", "export", "experiment"])
@pytest.mark.parametrize(
    "path, value, needle",
    [
        (("heads_spec", "obs_dim"), DELETE, "heads_spec has no 'obs_dim'"),
        (("heads_spec", "num_actions"), "4", "heads_spec['num_actions'] must be"),
        (("heads_spec", "option_names"), [], "heads_spec['option_names'] must be"),
        (("heads_spec", "obs_dim"), 10**7, "heads_spec['obs_dim'] is 10000000"),
        (("models",), [1], "models is a list, expected a dict"),
        (("models", "heads"), "weights", "models['heads'] is a str"),
    ],
    ids=[
        "no-obs_dim",
        "num_actions-str",
        "no-options",
        "huge-obs_dim",
        "models-list",
        "heads-str",
    ],  # fmt: skip
)
def test_a_tampered_bundle_is_refused_by_every_command_that_reads_heads(
    bundle, tmp_path, capsys, command, path, value, needle
):
    heads = {k: v for k, v in bundle.items() if k in ("config", "models", "heads_spec")}
    heads["models"] = {"heads": bundle["models"]["heads"]}
    ckpt = tampered(heads, path, value, tmp_path / "x.pt")
    argv = {
        "eval": ["eval", "--checkpoint", str(ckpt), *EVAL],
        "export": ["export", str(ckpt), "--out", str(tmp_path / "h.pt")],
        "experiment": [
            "experiment",
            "windy-fig2",
            "--checkpoint",
            str(ckpt),
            "--out",
            str(tmp_path / "e"),
            "--no-progress",
        ],  # fmt: skip
    }[command]
    refused(run(argv, capsys), command, needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.pt"]


# Tampering a real checkpoint's entries with Hypothesis: any entry a resume loads, changed in
# type or shape or removed, is a one-line refusal.


def _leaves(node: Any, path: tuple = ()) -> list[tuple]:
    """Paths to every entry of the resume state (dict keys, list items, leaves)."""
    out = [path] if path else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _leaves(v, (*path, k))
    elif isinstance(node, list) and len(node) <= 4:
        for i, v in enumerate(node):
            out += _leaves(v, (*path, i))
    return out


RESUMED = ("models", "optimizers", "counters", "rng", "learner", "first_visit", "stats", "replay",
           "env", "carrier")  # fmt: skip
IGNORED = (("rng", "cuda"),)  # restored only where CUDA is available


def _mutations(value: Any) -> st.SearchStrategy:
    """Removal, or a value of another type; a tensor of another shape or dtype."""
    others = {  # of another type than the entry's (an int stands for a float: not here)
        bool: ["x", None, 7],
        int: ["x", None, 1.5],
        float: ["x", None, [1.0]],
        str: [None, 1.5],
        type(None): ["x", [1]],
        dict: ["x", [], None],
        list: ["x", {}, None],
        tuple: ["x", {}, None],
    }
    if isinstance(value, torch.Tensor):
        shapes = [(), (value.numel() + 1,), (*value.shape, 2), (7, 3)]
        shapes = [s for s in shapes if tuple(s) != tuple(value.shape)]
        other = torch.float64 if value.dtype != torch.float64 else torch.int32
        changed = [torch.zeros(s, dtype=value.dtype) for s in shapes] + [value.to(other)]
        return st.sampled_from([DELETE, "x", None, *changed])
    kind = next(k for k in others if type(value) is k or (k is dict and isinstance(value, dict)))
    return st.sampled_from([DELETE, *others[kind]])


@pytest.fixture(scope="module")
def resume_paths(bundle) -> list[tuple]:
    paths = [p for k in RESUMED for p in _leaves(bundle[k], (k,))]
    return [p for p in paths if not any(p[: len(i)] == i for i in IGNORED)]


EXPLORE = os.environ.get("TASKVAR_FUZZ") == "explore"  # as tests/test_fuzz.py: new examples


@settings(
    max_examples=400 if EXPLORE else 20,
    deadline=None,
    database=None,
    derandomize=not EXPLORE,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
@pytest.mark.slow  # 20 refused resumes
def test_hypothesis_tampering_with_any_resumed_entry_is_a_one_line_refusal(
    data, bundle, resume_paths, tmp_path, capsys
):
    path = data.draw(st.sampled_from(resume_paths), label="entry")
    node = bundle
    for k in path:
        node = node[k]
    value = data.draw(_mutations(node), label="value")
    example = Path(tempfile.mkdtemp(dir=tmp_path))  # tmp_path is shared by the examples
    ckpt = tampered(bundle, path, value, example / "h.pt")
    out = example / "o"
    refused(
        run(["train", "--resume", str(ckpt), "--out", str(out), "--no-progress"], capsys), "train"
    )
    assert not out.exists()


@settings(
    max_examples=200 if EXPLORE else 15,
    deadline=None,
    database=None,
    derandomize=not EXPLORE,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
@pytest.mark.slow  # 15 refused evals
def test_hypothesis_tampering_with_what_eval_reads_is_a_one_line_refusal(
    data, bundle, tmp_path, capsys
):
    """The heads bundle's entries that ``eval`` and ``export`` build from: the heads' tensors and
    ``heads_spec`` (a config key left out takes its default, as for a checkpoint of an earlier
    version; a wrong one is the config's own one-line error)."""
    heads = {"config": bundle["config"], "models": {"heads": bundle["models"]["heads"]}}
    heads["heads_spec"] = bundle["heads_spec"]
    paths = [p for k in ("models", "heads_spec") for p in _leaves(heads[k], (k,))]
    path = data.draw(st.sampled_from(paths), label="entry")
    node = heads
    for k in path:
        node = node[k]
    value = data.draw(_mutations(node), label="value")
    if value is DELETE and path in (("heads_spec",), ("heads_spec", "option_input_mask")):
        return  # optional: a bundle without heads_spec (older) reads it from its env
    example = Path(tempfile.mkdtemp(dir=tmp_path))
    ckpt = tampered(heads, path, value, example / "h.pt")
    refused(run(["eval", "--checkpoint", str(ckpt), *EVAL], capsys), "eval")
    refused(run(["export", str(ckpt), "--out", str(example / "x.pt")], capsys), "export")
    assert sorted(p.name for p in example.iterdir()) == ["h.pt"]


def test_resume_of_an_untouched_checkpoint_still_works(run_dir, tmp_path, capsys):
    """The checks refuse only what does not fit: the periodic checkpoint resumes to the end."""
    ckpt = run_dir / "checkpoint_000000200.pt"
    status, lines = run(
        ["train", "--resume", str(ckpt), "--out", str(tmp_path / "r"), "--no-progress"], capsys
    )
    assert status == 0, lines
    a, b = load_checkpoint(tmp_path / "r" / "final.pt"), load_checkpoint(run_dir / "final.pt")
    assert a["counters"] == b["counters"]
    for k, v in b["models"]["heads"].items():
        assert torch.equal(a["models"]["heads"][k], v), k


# --------------------------------------------------------------------------------------------
# config: every number in a finite, bounded range; nothing allocated that cannot exist


@pytest.mark.parametrize(
    "override, needle",
    [
        ("train.robustness_tau=nan", "train.robustness_tau must be a finite number"),
        ("train.gamma=1.0", "train.gamma must be a finite number in [0.0, 1.0)"),
        ("train.lr=inf", "train.lr must be a finite number"),
        ("seed=4294967296", "seed must be an integer in [0, 4294967295]"),
        ("seed=-1", "seed must be an integer in [0, 4294967295]"),
        ("env.num_envs=9223372036854775808", "env.num_envs must be in [1, 2147483647]"),
        ("env.windy.horizon=100000000000000000000", "env.windy.horizon must be in [1, 1073741823]"),
        ("heads.hidden=[100000000000000000000]", "heads.hidden[0] must be in [1, 1048576]"),
        ("env.windy.patch_radius=100000", "env.windy.patch_radius must be in [0, 4096]"),
        ("env.num_envs=1000000000", "env.num_envs asks for too much memory"),
        ("train.buffer_size=1000000000000", "train.buffer_size asks for too much memory"),
        ("heads.hidden=[100000,100000]", "heads.hidden asks for too much memory"),
        ("device=meta", "device='meta' cannot run taskvar_torch"),
        ("device=xpu", "device='xpu' cannot run taskvar_torch"),
        ("device=hpu", "device='hpu' cannot run taskvar_torch"),
        ("device=lazy", "device='lazy' cannot run taskvar_torch"),
        # more of the same classes
        ("train.robustness_gamma=1.0", "train.robustness_gamma must be a finite number"),
        ("train.eps_start=nan", "train.eps_start must be a finite number"),
        ("train.mu_bar_temperature=inf", "train.mu_bar_temperature must be a finite number"),
        ("train.max_grad_norm=inf", "train.max_grad_norm must be a finite number"),
        ("train.total_frames=100000000000000000000", "train.total_frames must be in [0, "),
        ("train.seeds=2000", "train.seeds must be in [1, 1024]"),
        ("seed=4294967295", "uses seeds up to 4294967300"),
        (
            "env.windy.layout=generated env.windy.height=100000 env.windy.width=100000",
            "env.windy.height must be in [1, 4096]",
        ),
        (
            "env.windy.layout=generated env.windy.height=4096 env.windy.width=4096",
            "env.windy.layout has 16777216 cells",
        ),
        (
            "env.windy.obs_encoding=coords_patch env.windy.patch_radius=50",
            "env.windy.patch_radius must be in [0, ",
        ),
        pytest.param(  # builds the 1000x1000 layout: ~5 s
            "env.windy.layout=generated env.windy.height=1000 env.windy.width=1000",
            "env.windy asks for too much memory",
            marks=pytest.mark.slow,
        ),
        ("train.frames_per_batch=2000000000", "asks for too much memory"),
        ("train.seeds=1024", "asks for too much memory"),
        ("device=cuda:99", "device='cuda:99'"),
        ("device=nonsense", "device must be"),
    ],
)
def test_a_config_out_of_range_is_refused_before_any_work(override, needle, tmp_path, capsys):
    if override.startswith("device=cuda") and torch.cuda.device_count() > 99:
        pytest.skip("this machine has 100 GPUs")
    out = tmp_path / "run"
    argv = ["train", C, "--out", str(out), *T, *override.split(), "--no-progress"]
    refused(run(argv, capsys), "train", needle)
    assert not out.exists()


@pytest.mark.parametrize("override", ["device=meta", "device=xpu", "device=lazy"])
def test_a_device_torch_cannot_use_is_refused_on_resume(override, run_dir, tmp_path, capsys):
    argv = ["train", "--resume", str(run_dir / "final.pt"), "--out", str(tmp_path / "o"), override]
    refused(run(argv, capsys), "train", "cannot run taskvar_torch")


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--episodes", str(10**12)], "--episodes asks for too much memory"),
        (["--seed", str(2**32)], "--seed must be an integer in [0, 4294967295]"),
        (["--seed", "-1"], "--seed must be an integer in [0, 4294967295]"),
        (["--threads", "100000"], "--threads must be in [1, "),
        (["--threads", "0"], "--threads must be in [1, "),
        (["--episodes", "0"], "--episodes must be >= 1"),
    ],
)
def test_eval_flags_out_of_range_are_refused(argv, needle, run_dir, capsys):
    refused(run(["eval", "--checkpoint", str(run_dir / "final.pt"), *argv], capsys), "eval", needle)


@pytest.mark.slow  # a taskvar process of its own (~4 s of imports)
def test_threads_beyond_the_machine_never_reach_torch(tmp_path):
    """``--threads 100000`` crashed ``torch.set_num_threads``: refused in a process of its own."""
    r = taskvar("train", C, "--out", str(tmp_path / "o"), "--threads", "100000")
    assert r.returncode == 2, r.stderr[-2000:]
    one_line(r.stderr, "--threads must be in [1, ")


def test_a_seed_is_used_in_full_or_refused_never_wrapped(run_dir, tmp_path, capsys):
    """Seeds 0 and 2**32 played the same episodes; now 2**32 is refused everywhere and the
    largest seed plays other episodes than seed 0."""
    from taskvar_torch import rng

    assert not torch.equal(
        rng.sub_env_key(0, torch.arange(4)), rng.sub_env_key(rng.MAX_SEED, torch.arange(4))
    )
    with pytest.raises(ValueError, match="seed must be an integer"):
        rng.sub_env_key(2**32, torch.arange(4))
    for gid in GYM_IDS:
        env = gym.make(gid)
        with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 4294967295\]"):
            env.reset(seed=2**32)
        with pytest.raises(ValueError, match="seed must be an integer"):
            env.reset(seed=-1)


# --------------------------------------------------------------------------------------------
# the CLI: a plugin, a bug, memory


def _broken_plugin(tmp_path: Path, monkeypatch, body: str):
    """A family entry point whose module runs ``body`` on import; the registry reloads."""
    import importlib.metadata as md

    import taskvar_torch.contract as fams

    (tmp_path / "bad_plugin.py").write_text(body)
    monkeypatch.syspath_prepend(str(tmp_path))
    ep = md.EntryPoint("bad_plugin", "bad_plugin:family", fams.ENTRY_POINT_GROUP)
    installed = fams._entry_points()
    monkeypatch.setattr(fams, "_entry_points", lambda: [ep, *installed])
    monkeypatch.setattr(fams.FAMILIES, "_entry_points_loaded", False)
    monkeypatch.setattr(fams.FAMILIES, "broken", {})
    monkeypatch.delitem(fams.FAMILIES._families, "taxi", raising=False)  # an entry point: reloaded
    monkeypatch.delitem(sys.modules, "bad_plugin", raising=False)


@pytest.mark.parametrize(
    "body, reason",
    [
        ("import sys\nsys.exit(3)\n", "it called sys.exit(3) on import"),
        ("raise RuntimeError('no GPU here')\n", "RuntimeError: no GPU here"),
        (
            "import os\nos.environ['X'] = '1'\nfamily = 42\n",
            "TypeError: 'int' object is not callable",
        ),
        ("raise KeyboardInterrupt\n", "it raised KeyboardInterrupt on import"),
    ],
)
def test_a_plugin_failing_on_import_is_a_warning_naming_it(
    body, reason, tmp_path, monkeypatch, capsys
):
    """Imported only when its family is asked for (issue 58): a command of another family never
    imports it; one that names it gets one warning and a one-line refusal naming it."""
    import warnings

    _broken_plugin(tmp_path, monkeypatch, body)
    taxi = str(ROOT / "configs" / "taxi.yaml")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        outcome = run(["train", taxi, "--out", str(tmp_path / "o"), "seed=-1"], capsys)
    refused(outcome, "train", "seed must be")
    assert not [w for w in caught if "bad_plugin" in str(w.message)]
    assert "bad_plugin" not in sys.modules
    with pytest.warns(UserWarning, match="family 'bad_plugin'") as caught:
        argv = ["train", taxi, "--out", str(tmp_path / "o"), "family=bad_plugin"]
        outcome = run(argv, capsys)
    refused(outcome, "train", "'bad_plugin'", reason)
    assert any(reason in str(w.message) for w in caught), [str(w.message) for w in caught]


def test_a_bug_prints_its_traceback_and_says_it_is_one(monkeypatch, capsys):
    """Not the input's fault: the traceback, then one line naming it a bug and where to report."""

    def broken(args):
        raise TypeError("unsupported operand")

    monkeypatch.setitem(cli.COMMANDS, "plot", cli.COMMANDS["plot"].__class__(
        "h", "d", cli.COMMANDS["plot"].add_arguments, broken))  # fmt: skip
    status, lines = run(["plot", "anything"], capsys)
    assert status == 1
    assert lines[0].startswith("Traceback") and "TypeError: unsupported operand" in lines
    assert lines[-1].startswith("taskvar plot: internal error (TypeError): this is a bug")
    assert "report it" in lines[-1]


@pytest.mark.parametrize("error", [MemoryError(), torch.OutOfMemoryError("CUDA out of memory")])
def test_running_out_of_memory_is_one_line(error, monkeypatch, capsys):
    def oom(args):
        raise error

    monkeypatch.setitem(cli.COMMANDS, "plot", cli.COMMANDS["plot"].__class__(
        "h", "d", cli.COMMANDS["plot"].add_arguments, oom))  # fmt: skip
    refused(run(["plot", "x"], capsys), "plot", "out of memory", "train.buffer_size")


# --------------------------------------------------------------------------------------------
# results folders: never silently replaced, never two runs mixed, never a file lost


@pytest.mark.parametrize("command", ["train", "eval", "export", "experiment", "sweep", "report"])
def test_an_empty_out_is_refused(command, run_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "config.yaml").write_text("mine: true\n")
    before = fingerprint(tmp_path)
    ckpt = str(run_dir / "final.pt")
    argv = {
        "train": ["train", C, *T],
        "eval": ["eval", "--checkpoint", ckpt, *EVAL],
        "export": ["export", ckpt],
        "experiment": ["experiment", "windy-fig2", "--checkpoint", ckpt],
        "sweep": ["sweep", C, "seed=0,1", "--backend", "local"],
        "report": ["report", str(run_dir)],
    }[command]
    refused(run([*argv, "--out", "", "--overwrite"], capsys), command, "--out is empty")
    assert fingerprint(tmp_path) == before


def test_overwrite_in_a_project_folder_keeps_its_files(tmp_path, capsys, monkeypatch):
    """``--out . --overwrite`` where ``config.yaml``, ``logs/`` and ``heads/`` are the user's
    own (no taskvar run): refused, every file as it was."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "config.yaml").write_text("my: project\n")
    for d in ("logs", "heads"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "notes.txt").write_text(d)
    before = fingerprint(tmp_path)
    outcome = run(["train", C, "--out", ".", *T, "--overwrite", "--no-progress"], capsys)
    refused(outcome, "train", "no taskvar run")
    assert fingerprint(tmp_path) == before


@pytest.mark.parametrize("command", ["eval", "experiment", "sweep"])
def test_results_into_a_folder_of_other_files_are_refused(
    command, run_dir, tmp_path, capsys, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    before = fingerprint(tmp_path)
    ckpt = str(run_dir / "final.pt")
    argv = {
        "eval": ["eval", "--checkpoint", ckpt, *EVAL],
        "experiment": ["experiment", "windy-fig2", "--checkpoint", ckpt, "--no-progress"],
        "sweep": ["sweep", C, "seed=0,1", "--backend", "local", "--no-progress"],
    }[command]
    refused(
        run([*argv, "--out", ".", "--overwrite"], capsys),
        command,
        "not taskvar results (notes.txt)",
    )
    assert fingerprint(tmp_path) == before


def test_export_onto_its_own_checkpoint_is_refused_and_it_still_resumes(run_dir, tmp_path, capsys):
    """``export R/final.pt --out R/final.pt --overwrite`` turned the training checkpoint into a
    heads bundle that cannot resume."""
    run_copy = tmp_path / "R"
    run_copy.mkdir()
    ckpt = run_copy / "final.pt"
    ckpt.write_bytes((run_dir / "final.pt").read_bytes())
    before = fingerprint(run_copy)
    refused(run(["export", str(ckpt), "--out", str(ckpt), "--overwrite"], capsys), "export",
            "is the checkpoint itself")  # fmt: skip
    other = run_copy / "other.pt"
    other.write_bytes((run_dir / "checkpoint_000000200.pt").read_bytes())
    before = fingerprint(run_copy)
    refused(run(["export", str(ckpt), "--out", str(other), "--overwrite"], capsys), "export",
            "is a training checkpoint")  # fmt: skip
    assert fingerprint(run_copy) == before
    assert "optimizers" in load_checkpoint(ckpt)


@pytest.mark.parametrize("command", ["eval", "experiment"])
def test_a_checkpoint_inside_out_is_refused(command, run_dir, tmp_path, capsys):
    folder = tmp_path / "R"
    folder.mkdir()
    (folder / "final.pt").write_bytes((run_dir / "final.pt").read_bytes())
    before = fingerprint(tmp_path)
    ckpt = str(folder / "final.pt")
    argv = {
        "eval": ["eval", "--checkpoint", ckpt, *EVAL],
        "experiment": ["experiment", "windy-fig2", "--checkpoint", ckpt, "--no-progress"],
    }[command]
    refused(run([*argv, "--out", str(folder), "--overwrite"], capsys), command)
    assert fingerprint(tmp_path) == before


def test_report_into_a_results_folder_it_reads_is_refused(run_dir, tmp_path, capsys):
    out = tmp_path / "E"
    assert (
        cli.main(["eval", "--checkpoint", str(run_dir / "final.pt"), *EVAL, "--out", str(out)]) == 0
    )
    capsys.readouterr()
    before = fingerprint(out)
    argv = ["report", str(out), "--out", str(out / "metrics.json"), "--overwrite"]
    refused(run(argv, capsys), "report", "lies in the results folder")
    assert fingerprint(out) == before


def test_a_second_eval_on_a_folder_in_use_is_refused(run_dir, tmp_path, capsys):
    """Two ``taskvar eval --out E`` at once both exited 0, one replacing the other."""
    out = tmp_path / "E"
    out.mkdir()
    fd = lock_folder(out)  # the first eval, still running
    try:
        argv = ["eval", "--checkpoint", str(run_dir / "final.pt"), *EVAL, "--out", str(out)]
        refused(run(argv, capsys), "eval", "in use by another taskvar run", f"pid {os.getpid()}")
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    finally:
        unlock_folder(out, fd)


def test_overwrite_leaves_no_file_of_the_earlier_results(run_dir, tmp_path, capsys):
    """``--overwrite`` kept an earlier ``regret_by_frames.csv/.png``: now the folder holds the
    new results only, the staging folder is gone."""
    out = tmp_path / "E"
    argv = ["eval", "--checkpoint", str(run_dir / "final.pt"), *EVAL, "--out", str(out)]
    assert cli.main(argv) == 0
    (out / "regret_by_frames.csv").write_text("frames,regret\n1,2\n")  # an earlier --by-frames
    assert cli.main([*argv, "--overwrite"]) == 0
    assert not (out / "regret_by_frames.csv").exists()
    assert (out / "metrics.json").is_file() and not (out / LOCK_NAME).exists()
    assert [p.name for p in tmp_path.iterdir()] == ["E"]


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_overwrite_with_a_symlinked_logs_folder_removes_the_link_only(run_dir, tmp_path, capsys):
    """``--overwrite`` with ``logs`` a symlink deleted ``final.pt``, then stopped."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.txt").write_text("not yours")
    out = tmp_path / "run"
    assert cli.main(["train", C, "--out", str(out), *TINY, "--no-progress"]) == 0
    import shutil

    shutil.rmtree(out / "logs")
    (out / "logs").symlink_to(elsewhere, target_is_directory=True)
    status, lines = run(
        ["train", C, "--out", str(out), *TINY, "--overwrite", "--no-progress"], capsys
    )
    assert status == 0, lines
    assert (out / "final.pt").is_file() and not (out / "logs").is_symlink()
    assert fingerprint(elsewhere) == {"keep.txt": hashlib.sha256(b"not yours").hexdigest()}


KILL_AT_WRITE = """
import os, signal
import taskvar_torch.experiments.bundle_eval as B
write_json = B.write_json
def killed(path, obj, *a, **k):  # episodes.csv is written: SIGKILL before metrics.json
    os.kill(os.getpid(), signal.SIGKILL)
B.write_json = killed
"""


@pytest.mark.slow  # a taskvar process of its own (~4 s of imports)
def test_sigkill_of_an_overwriting_eval_leaves_the_old_results_whole(run_dir, tmp_path, capsys):
    """Killed mid-write, the overwrite left the old ``metrics.json`` beside the new
    ``episodes.csv`` (and ``taskvar report`` read them); the next eval cleans up after it."""
    out = tmp_path / "E"
    argv = ["eval", "--checkpoint", str(run_dir / "final.pt"), *EVAL, "--out", str(out)]
    assert cli.main(argv) == 0
    before = fingerprint(out)
    r = taskvar(*argv, "--overwrite", "--episodes", "9", hook=KILL_AT_WRITE)
    assert r.returncode == -signal.SIGKILL
    after = fingerprint(out)
    after.pop(LOCK_NAME)  # the killed one's (unlocked by the kernel), not a result
    assert after == before
    assert cli.main([*argv, "--overwrite"]) == 0  # the killed one's staging folder is removed
    assert [p.name for p in tmp_path.iterdir()] == ["E"]


TERM_BEFORE_LOOP = """
import os, signal
import taskvar_torch.training as T
build = T.build_run
def term(*args, **kwargs):  # the folder is taken, the loop not started
    os.kill(os.getpid(), signal.SIGTERM)
    return build(*args, **kwargs)
T.build_run = term
"""


@pytest.mark.slow  # a taskvar process of its own (~4 s of imports)
def test_sigterm_before_the_loop_prints_one_line_and_leaves_no_folder(tmp_path):
    """SIGTERM in the first seconds exited 143 with no line and left a folder a rerun refused."""
    out = tmp_path / "run"
    r = taskvar("train", C, "--out", str(out), *TINY, "--no-progress", hook=TERM_BEFORE_LOOP)
    assert r.returncode == 128 + signal.SIGTERM, r.stderr[-2000:]
    one_line(r.stderr, "taskvar train: interrupted by SIGTERM")
    assert not out.exists()  # a rerun is not refused


TERM_IN_EVAL = """
import os, signal
import taskvar_torch.experiments.bundle_eval as B
write_csv = B.write_csv
def term(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGTERM)
    return write_csv(*args, **kwargs)
B.write_csv = term
"""


@pytest.mark.slow  # a taskvar process of its own (~4 s of imports)
def test_sigterm_during_an_overwriting_eval_prints_one_line_and_keeps_the_old_results(
    run_dir, tmp_path
):
    out = tmp_path / "E"
    argv = ["eval", "--checkpoint", str(run_dir / "final.pt"), *EVAL, "--out", str(out)]
    assert cli.main(argv) == 0
    before = fingerprint(out)
    r = taskvar(*argv, "--overwrite", hook=TERM_IN_EVAL)
    assert r.returncode == 128 + signal.SIGTERM, r.stderr[-2000:]
    one_line(r.stderr, "taskvar eval: interrupted by SIGTERM")
    assert fingerprint(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["E"]


def test_an_abandoned_results_folder_leaves_nothing_behind(tmp_path):
    """A refused or failed command removes the folder it created, and its staging folder."""
    folder = ResultsFolder(tmp_path / "new" / "E", overwrite=False, command="taskvar eval")
    staging = folder.acquire()
    (staging / "metrics.json").write_text("{}")
    folder.abandon()
    assert not (tmp_path / "new" / "E").exists() and list((tmp_path / "new").iterdir()) == []


@pytest.mark.parametrize("atomic", [True, False], ids=["renameat2", "two-renames"])
def test_results_are_swapped_in_whole(atomic, tmp_path, monkeypatch):
    """With the atomic exchange or without it (two renames), the folder ends up holding the new
    results only, and nothing is left beside it."""
    import taskvar_torch.run_folder as rf

    if not atomic:
        monkeypatch.setattr(rf, "_exchange", lambda a, b: False)
    out = tmp_path / "E"
    out.mkdir()
    (out / "metrics.json").write_text("old")
    (out / "stale.png").write_text("old")
    with ResultsFolder(out, overwrite=True, command="taskvar eval") as staging:
        (staging / "metrics.json").write_text("new")
    assert fingerprint(out) == {"metrics.json": hashlib.sha256(b"new").hexdigest()}
    assert [p.name for p in tmp_path.iterdir()] == ["E"]


# --------------------------------------------------------------------------------------------
# Gymnasium: reset() without a seed draws from entropy, as Gymnasium's own envs


def _episode(env: gym.Env, seed: int | None = None, steps: int = 12) -> list:
    obs, info = env.reset(seed=seed)
    trace = [np.asarray(obs).tolist(), str(info.get("instance"))]
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(1)
        trace.append(np.asarray(obs).tolist())
        if terminated or truncated:
            break
    return trace


@pytest.mark.parametrize("gid", GYM_IDS)
def test_two_unseeded_envs_play_different_episodes(gid):
    """``reset()`` without a seed always played seed 0 (Windy, Taxi)."""
    a, b = gym.make(gid), gym.make(gid)
    assert [_episode(a) for _ in range(3)] != [_episode(b) for _ in range(3)]


@pytest.mark.parametrize("gid", GYM_IDS)
def test_make_vec_without_a_seed_gives_different_sub_envs(gid):
    envs = gym.make_vec(gid, 3)
    obs, info = envs.reset()
    firsts = [str(np.asarray(o).tolist()) for o in obs]
    instances = [str(v) for v in info.get("instance", {}).values()] if "instance" in info else []
    assert len(set(firsts)) > 1 or len(set(instances)) > 1
    envs.close()


@pytest.mark.parametrize("gid", GYM_IDS)
def test_an_unseeded_reset_continues_the_seeded_stream(gid):
    """After ``reset(seed=s)``, ``reset()`` plays the stream's next episode, as a fresh env
    seeded ``s`` does; the same seed, the same episodes."""
    a, b = gym.make(gid), gym.make(gid)
    assert _episode(a, seed=11) == _episode(b, seed=11)
    assert _episode(a) == _episode(b)
    assert _episode(a) != _episode(a, seed=11)
