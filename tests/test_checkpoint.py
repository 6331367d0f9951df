"""Checkpoint bundles: round trips, refusals (code, truncation, foreign files, mismatches), atomicity.

In the style of Stable-Baselines3's ``test_save_load.py``: every error path is exercised and its
one-line message checked.
"""

from __future__ import annotations

import builtins
import os
import random
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from taskvar_torch import checkpoint as ckpt
from taskvar_torch.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    CheckpointError,
    load_checkpoint,
    make_bundle,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from taskvar_torch.checkpoint.checks import load_state_dicts
from taskvar_torch.config import Config, apply_overrides, config_from_dict

torch.set_num_threads(1)


def _net(width: int = 16) -> nn.Module:
    return nn.Sequential(nn.Linear(5, width), nn.ReLU(), nn.Linear(width, 3))


def _trained(seed: int = 0, steps: int = 3) -> tuple[nn.Module, nn.Module, torch.optim.Optimizer]:
    torch.manual_seed(seed)
    net, target = _net(), _net()
    target.load_state_dict(net.state_dict())
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    for _ in range(steps):
        _adam_step(net, opt)
    return net, target, opt


def _adam_step(net: nn.Module, opt: torch.optim.Optimizer) -> None:
    x = torch.linspace(-1, 1, 40).reshape(8, 5)
    loss = net(x).pow(2).mean()
    opt.zero_grad()
    loss.backward()
    opt.step()


def _one_line(info: pytest.ExceptionInfo, *parts: str) -> str:
    msg = str(info.value)
    assert "\n" not in msg, msg
    for part in parts:
        assert part in msg, f"{part!r} not in {msg!r}"
    return msg


def _assert_same_tree(a, b) -> None:
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    elif isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _assert_same_tree(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _assert_same_tree(x, y)
    else:
        assert a == b


# ---------------------------------------------------------------- round trips


def test_round_trip_restores_outputs_optimizer_state_and_training(tmp_path: Path):
    net, target, opt = _trained()
    cfg = config_from_dict({})  # the default config, its family section included
    path = save_checkpoint(
        tmp_path / "run" / "final.pt",  # parent folder is created
        make_bundle(
            cfg,
            models={"averaging": net, "averaging_target": target},
            optimizers={"averaging": opt},
            counters={"frames": 1234, "updates": 56},
        ),
    )
    bundle = load_checkpoint(path, expected_config=cfg)
    assert bundle["format"] == FORMAT and bundle["format_version"] == FORMAT_VERSION
    assert bundle["counters"] == {"frames": 1234, "updates": 56}
    assert config_from_dict(bundle["config"]) == cfg
    assert {"taskvar_torch", "torch", "torchrl", "tensordict", "python"} <= set(bundle["versions"])

    torch.manual_seed(99)  # different initial weights
    net2, target2 = _net(), _net()
    opt2 = torch.optim.Adam(net2.parameters(), lr=1e-2)
    load_state_dicts(
        bundle,
        models={"averaging": net2, "averaging_target": target2},
        optimizers={"averaging": opt2},
    )
    x = torch.randn(7, 5)
    assert torch.equal(net(x), net2(x))
    assert torch.equal(target(x), target2(x))
    _assert_same_tree(opt.state_dict(), opt2.state_dict())
    # training continues identically, bit for bit
    _adam_step(net, opt)
    _adam_step(net2, opt2)
    for p, q in zip(net.parameters(), net2.parameters()):
        assert torch.equal(p, q)


def test_saved_file_is_plain_data_for_weights_only_torch_load(tmp_path: Path):
    net, _, opt = _trained()
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(Config(), {"n": net}, {"n": opt}))
    data = torch.load(path, weights_only=True)  # would raise on any non-allowlisted object
    assert data["config"]["family"] == "windy"


def test_rng_state_round_trip_through_a_file(tmp_path: Path):
    gen = torch.Generator().manual_seed(5)
    torch.manual_seed(1)
    np.random.seed(2)
    random.seed(3)
    state = rng_state({"env": gen})
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(Config(), {}, rng=state))

    def draw():
        return (
            torch.rand(3).tolist(),
            np.random.rand(3).tolist(),
            [random.random() for _ in range(3)],
            torch.rand(3, generator=gen).tolist(),
        )

    first = draw()
    draw()  # advance everything
    set_rng_state(load_checkpoint(path)["rng"], {"env": gen})
    assert draw() == first
    with pytest.raises(CheckpointError, match="no state for generator 'other'"):
        set_rng_state(state, {"other": torch.Generator()})


def test_replay_contents_as_plain_tensors(tmp_path: Path):
    replay = {"observation": torch.randn(10, 4), "action": torch.arange(10), "size": 10}
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(Config(), {}, replay=replay))
    _assert_same_tree(load_checkpoint(path)["replay"], replay)


# ---------------------------------------------------------------- refusals on load


class _RunsCode:
    """Unpickling this calls ``fn(*args)``: the classic code-execution payload."""

    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return (self.fn, self.args)


def _payloads(marker: Path):
    return {
        "os.system": _RunsCode(os.system, (f"touch '{marker}'",)),
        "builtins.exec": _RunsCode(builtins.exec, (f"open({str(marker)!r}, 'w').write('pwned')",)),
    }


@pytest.mark.parametrize("kind", ["os.system", "builtins.exec"])
@pytest.mark.parametrize("tagged", [False, True], ids=["bare", "with_format_tag"])
def test_file_that_executes_code_is_refused_and_nothing_runs(
    tmp_path: Path, kind: str, tagged: bool
):
    # control: the payload really executes code when loaded unsafely
    control_marker = tmp_path / "control_marker"
    torch.save({"x": _payloads(control_marker)[kind]}, tmp_path / "control.pt")
    torch.load(tmp_path / "control.pt", weights_only=False)
    assert control_marker.exists()

    marker = tmp_path / "marker"
    evil = {"x": _payloads(marker)[kind]}
    if tagged:
        evil.update(format=FORMAT, format_version=FORMAT_VERSION, config={})
    path = tmp_path / "evil.pt"
    torch.save(evil, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    _one_line(info, "refusing to load", str(path), "not a plain-data checkpoint", "code or objects")
    assert not marker.exists(), "unpickling executed code"


def test_truncated_file_is_a_one_line_error(tmp_path: Path):
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(Config(), {"n": _net()}))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    _one_line(info, "truncated or corrupt", str(path))


@pytest.mark.parametrize(
    "content", [b"", b"hello, not a torch file at all"], ids=["empty", "garbage"]
)
def test_empty_or_garbage_file_is_a_one_line_error(tmp_path: Path, content: bytes):
    path = tmp_path / "c.pt"
    path.write_bytes(content)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    _one_line(info, "truncated or corrupt", str(path))


@pytest.mark.parametrize(
    "obj, what",
    [
        (torch.zeros(3), "a Tensor"),
        ({"weight": torch.zeros(3)}, "a dict with keys ['weight']"),
        ({"format": "sb3", "config": {}}, "a dict"),
    ],
    ids=["bare_tensor", "state_dict", "other_format"],
)
def test_foreign_torch_file_is_not_a_taskvar_checkpoint(tmp_path: Path, obj, what: str):
    path = tmp_path / "c.pt"
    torch.save(obj, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    _one_line(info, "not a taskvar_torch checkpoint", str(path), what)


def test_newer_format_version_is_refused(tmp_path: Path):
    path = tmp_path / "c.pt"
    torch.save({"format": FORMAT, "format_version": FORMAT_VERSION + 1, "config": {}}, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    _one_line(info, f"format version {FORMAT_VERSION + 1}", f"up to {FORMAT_VERSION}", str(path))


def test_missing_file_and_directory(tmp_path: Path):
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(tmp_path / "nope.pt")
    _one_line(info, "does not exist", "nope.pt")
    with pytest.raises(CheckpointError, match="not a file"):
        load_checkpoint(tmp_path)


def test_config_mismatch_names_the_key_and_both_values(tmp_path: Path):
    cfg = Config()
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(cfg, {}))
    other = apply_overrides(cfg, ["env.windy.layout=middle_exits"])
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path, expected_config=other)
    _one_line(
        info, "trained with env.windy.layout='default'", "the config says 'middle_exits'", str(path)
    )

    several = apply_overrides(cfg, ["train.lr=0.5", "heads.hidden=[8]", "seed=3"])
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path, expected_config=several)
    _one_line(info, "also differ")


def test_runtime_keys_may_differ_unless_asked(tmp_path: Path):
    cfg = Config()
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(cfg, {}))
    longer = apply_overrides(cfg, ["train.total_frames=999999", "eval.episodes=5", "device=cuda"])
    load_checkpoint(path, expected_config=longer)  # resuming longer / evaluating elsewhere is fine
    with pytest.raises(CheckpointError, match="trained with train.total_frames=200000 but"):
        load_checkpoint(path, expected_config=longer, ignore=("device", "eval"))
    with pytest.raises(
        CheckpointError, match="trained with device='cpu' but the config says 'cuda'"
    ):
        load_checkpoint(path, expected_config=longer, ignore=())


def test_state_dict_that_does_not_fit_is_a_clear_error(tmp_path: Path):
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(Config(), {"averaging": _net(16)}))
    bundle = load_checkpoint(path)
    with pytest.raises(CheckpointError) as info:
        load_state_dicts(bundle, {"averaging": _net(32)})
    _one_line(info, "models['averaging']", "does not fit")
    with pytest.raises(CheckpointError, match=r"no models\['options'\]"):
        load_state_dicts(bundle, {"options": _net(16)})


# ---------------------------------------------------------------- refusals on save, atomicity


def _previous(tmp_path: Path) -> tuple[Path, bytes]:
    path = save_checkpoint(
        tmp_path / "c.pt", make_bundle(Config(), {"n": _net()}, counters={"frames": 1})
    )
    return path, path.read_bytes()


def _assert_intact(tmp_path: Path, path: Path, before: bytes) -> None:
    assert path.read_bytes() == before
    assert load_checkpoint(path)["counters"] == {"frames": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.pt"], "temporary file left behind"


@pytest.mark.parametrize(
    "bad, where",
    [
        (lambda: None, "bundle['counters']['bad']"),
        (np.float64(1.5), "bundle['counters']['bad']"),
        (np.zeros(2), "bundle['counters']['bad']"),
        (object(), "bundle['counters']['bad']"),
    ],
    ids=["lambda", "numpy_scalar", "numpy_array", "object"],
)
def test_bundle_with_non_plain_data_is_refused_and_previous_file_kept(tmp_path, bad, where):
    path, before = _previous(tmp_path)
    with pytest.raises(CheckpointError) as info:
        save_checkpoint(path, make_bundle(Config(), {}, counters={"frames": 2, "bad": bad}))
    _one_line(info, "cannot save", where, "plain data")
    _assert_intact(tmp_path, path, before)


def test_bundle_without_config_or_with_reserved_keys_is_refused(tmp_path: Path):
    with pytest.raises(CheckpointError, match="no 'config'"):
        save_checkpoint(tmp_path / "c.pt", {"models": {}})
    with pytest.raises(CheckpointError, match="'format' is reserved"):
        save_checkpoint(tmp_path / "c.pt", {"config": {}, "format": "x"})
    assert list(tmp_path.iterdir()) == []


def test_failed_rename_keeps_previous_file_and_removes_temp(tmp_path: Path, monkeypatch):
    path, before = _previous(tmp_path)

    def fail(*args, **kwargs):
        raise OSError("disk on fire")

    monkeypatch.setattr(ckpt.os, "replace", fail)
    with pytest.raises(OSError, match="disk on fire"):
        save_checkpoint(path, make_bundle(Config(), {"n": _net()}, counters={"frames": 2}))
    monkeypatch.undo()
    _assert_intact(tmp_path, path, before)


def test_crash_while_writing_keeps_previous_file_and_removes_temp(tmp_path: Path, monkeypatch):
    path, before = _previous(tmp_path)
    real_save = torch.save

    def half_then_crash(obj, f, *args, **kwargs):
        real_save(obj, f, *args, **kwargs)
        f.truncate(10)
        raise KeyboardInterrupt  # e.g. the run is killed mid-write

    monkeypatch.setattr(ckpt.torch, "save", half_then_crash)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, make_bundle(Config(), {"n": _net()}, counters={"frames": 2}))
    monkeypatch.undo()
    _assert_intact(tmp_path, path, before)


def test_overwrite_replaces_the_file(tmp_path: Path):
    path, _ = _previous(tmp_path)
    save_checkpoint(path, make_bundle(Config(), {}, counters={"frames": 2}))
    assert load_checkpoint(path)["counters"] == {"frames": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.pt"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_tensors_load_on_cpu(tmp_path: Path):
    net = _net().cuda()
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(Config(device="cuda"), {"n": net}))
    bundle = load_checkpoint(path, map_location="cpu")
    assert all(t.device.type == "cpu" for t in bundle["models"]["n"].values())
    assert len(bundle["rng"]["cuda"]) == torch.cuda.device_count()
    set_rng_state(bundle["rng"])


def test_saved_file_has_the_usual_permissions(tmp_path: Path):
    plain = tmp_path / "plain"
    plain.write_bytes(b"")
    path = save_checkpoint(tmp_path / "c.pt", make_bundle(Config(), {}))
    assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777
