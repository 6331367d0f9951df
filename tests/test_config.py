"""Strict configs: every file loads, misspelt keys and bad values are one-line errors naming them."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from taskvar_torch.config import (
    METHODS,
    Config,
    EnvConfig,
    EvalConfig,
    ExperimentConfig,
    HeadsConfig,
    TrainConfig,
    apply_overrides,
    config_from_dict,
    config_help,
    config_to_dict,
    field_docs,
    load_config,
    save_config_yaml,
)
from taskvar_torch.config.loader import config_schema
from taskvar_torch.families.wargus import WargusConfig, WargusSubtasks
from taskvar_torch.families.wargus.family import Fig4Config, WargusSection
from taskvar_torch.families.windy import WindyGridEnv, fig2_metrics
from taskvar_torch.families.windy import fig2 as windy_fig2
from taskvar_torch.families.windy.config import Fig2Config
from taskvar_torch.families.windy.family import EXACT_ORACLE_CELLS, windy_env_kwargs, windy_layout
from taskvar_torch.study.scale import load_scale_config
from taskvar_torch.study.scale_config import ScaleConfig

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
# Training/experiment configs (the `Config` schema); `scale.yaml` is the scale experiment's own
# schema (`study.scale_config.ScaleConfig`), checked in tests/study/test_experiments_scale.py.
CONFIG_FILES = sorted(p for p in CONFIG_DIR.glob("*.yaml") if p.name != "scale.yaml")
SCALE_CONFIG = CONFIG_DIR / "scale.yaml"
WINDY = CONFIG_DIR / "windy.yaml"

# Keys only one family reads: a config file of the other family must not set them (
# no config key that nothing reads).
WINDY_ONLY = (
    "env.windy.layout",
    "env.windy.height",
    "env.windy.width",
    "env.windy.num_exits",
    "env.windy.wall_col",
    "env.windy.wind_cells_per_exit",
    "env.windy.horizon",
    "env.windy.obs_encoding",
    "env.windy.patch_radius",
    "experiment.episodes_per_run",
)
WARGUS_ONLY = (
    "env.wargus",
    "train.robustness_gamma",
    "train.robustness_tau",
    "train.robustness_target",
    "train.hierarchy_root_policy",
    "experiment.trials",
    "experiment.learning_episodes_per_trial",
    "experiment.test_episodes_per_trial",
)


def _raises_one_line(match_all: list[str], fn, *args, **kwargs) -> str:
    with pytest.raises(ValueError) as info:
        fn(*args, **kwargs)
    msg = str(info.value)
    assert "\n" not in msg, msg
    for part in match_all:
        assert part in msg, f"{part!r} not in {msg!r}"
    return msg


def _flat_keys(node, prefix: str = "") -> list[str]:
    out = []
    for k, v in node.items():
        out.append(f"{prefix}{k}")
        if isinstance(v, dict):
            out.extend(_flat_keys(v, f"{prefix}{k}."))
    return out


def _write(tmp_path: Path, text: str, name: str = "c.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


# ---------------------------------------------------------------- every shipped file


def test_configs_folder_has_the_spec_files():
    names = {p.name for p in CONFIG_FILES}
    for required in (
        "windy.yaml",
        "windy_middle_exits.yaml",
        "windy_whole_column.yaml",
        "windy_large.yaml",
        "windy_xl.yaml",
        "wargus.yaml",
        "wargus_large.yaml",
        "taxi.yaml",
    ):
        assert required in names


@pytest.mark.parametrize("path", CONFIG_FILES, ids=lambda p: p.name)
def test_every_config_file_loads_strictly(path: Path):
    cfg = load_config(path)
    assert isinstance(cfg, Config)
    quick = load_config(path, quick=True)
    assert quick.train.total_frames <= cfg.train.total_frames
    assert quick.experiment.runs <= cfg.experiment.runs
    # the file's keys are exactly schema keys, and they round-trip
    raw = OmegaConf.to_container(OmegaConf.load(path))
    schema = set(_flat_keys(config_to_dict(config_schema(cfg.family)(family=cfg.family))))
    assert set(_flat_keys(raw)) <= schema
    assert config_from_dict(config_to_dict(cfg)) == cfg


@pytest.mark.parametrize("path", CONFIG_FILES, ids=lambda p: p.name)
def test_config_files_set_no_key_of_the_other_family(path: Path):
    cfg = load_config(path)
    keys = _flat_keys(OmegaConf.to_container(OmegaConf.load(path)))
    foreign = WARGUS_ONLY if cfg.family == "windy" else WINDY_ONLY
    unread = [k for k in keys if any(k == f or k.startswith(f + ".") for f in foreign)]
    assert not unread, f"{path.name} sets keys a {cfg.family} run never reads: {unread}"


@pytest.mark.parametrize(
    "path", [p for p in CONFIG_FILES if p.name.startswith("windy")], ids=lambda p: p.name
)
def test_windy_config_files_build_their_environment(path: Path):
    cfg = load_config(path, ["env.num_envs=2"])
    env = WindyGridEnv(**windy_env_kwargs(cfg))
    td = env.reset()
    assert td["observation"].shape[0] == 2
    layout = windy_layout(cfg.env.windy)
    assert env.layout == layout


def test_scaled_up_windy_files_have_the_spec_sizes():
    large = windy_layout(load_config(CONFIG_DIR / "windy_large.yaml").env.windy)
    xl = windy_layout(load_config(CONFIG_DIR / "windy_xl.yaml").env.windy)
    assert (large.height, large.width, large.num_exits) == (25, 25, 2)
    assert (xl.height, xl.width, xl.num_exits) == (51, 51, 4)
    assert load_config(CONFIG_DIR / "windy_large.yaml").env.windy.obs_encoding == "coords_patch"
    assert (
        windy_layout(load_config(CONFIG_DIR / "windy_middle_exits.yaml").env.windy).rows[1]
        == "SW.GG"
    )
    wl = load_config(CONFIG_DIR / "wargus_large.yaml").env.wargus
    assert (wl.size, wl.num_patrols) == (64, 3)
    # robustness critics look ~100 steps ahead (heads/robustness.py "Scale")
    assert load_config(CONFIG_DIR / "wargus.yaml").train.robustness_gamma == 0.99


# ---------------------------------------------------------------- unknown keys


def test_misspelt_top_level_key_is_an_error_naming_it(tmp_path: Path):
    p = _write(tmp_path, "famly: windy\n")
    msg = _raises_one_line(["'famly'", "family", "seed", "experiment", str(p)], load_config, p)
    assert "did you mean 'family'" in msg


@pytest.mark.parametrize(
    "text, key, allowed",
    [
        ("train:\n  lrr: 0.01\n", "train.lrr", "updates_per_batch"),
        ("family: wargus\nenv:\n  wargus:\n    sigth: 3\n", "env.wargus.sigth", "shoot_range"),
        ("heads:\n  hiden: [3]\n", "heads.hiden", "activation"),
    ],
)
def test_misspelt_nested_key_is_an_error_naming_the_dotted_key(tmp_path, text, key, allowed):
    p = _write(tmp_path, text)
    _raises_one_line([repr(key), allowed], load_config, p)


def test_section_given_a_scalar_is_an_error_naming_it(tmp_path: Path):
    _raises_one_line(
        ["'heads'", "hidden", "activation"], load_config, _write(tmp_path, "heads: 3\n")
    )


def test_missing_file_and_non_mapping_file_are_errors(tmp_path: Path):
    _raises_one_line(["does not exist"], load_config, tmp_path / "nope.yaml")
    _raises_one_line(["mapping"], load_config, _write(tmp_path, "- 1\n- 2\n"))


def test_wrong_type_in_file_names_key_and_file(tmp_path: Path):
    p = _write(tmp_path, "seed: abc\n")
    _raises_one_line(["'seed'", str(p), "Integer"], load_config, p)
    p = _write(tmp_path, "train:\n  batch_size: 2.5\n", "d.yaml")
    _raises_one_line(["'train.batch_size'"], load_config, p)
    p = _write(tmp_path, "seed: 1\nheads:\n  activation: relu\n  hidden: [8, x]\n", "e.yaml")
    _raises_one_line(["'heads.hidden'", "[8, 'x']", str(p)], load_config, p)


# ---------------------------------------------------------------- overrides


def test_override_applies_and_leaves_the_rest_alone():
    base = load_config(WINDY)
    cfg = load_config(
        WINDY, ["train.lr=0.01", "heads.hidden=[32,16]", "env.windy.layout=middle_exits"]
    )
    assert cfg.train.lr == 0.01
    assert cfg.heads.hidden == (32, 16)
    assert cfg.env.windy.layout == "middle_exits"
    assert (
        dataclasses.replace(
            cfg,
            train=dataclasses.replace(cfg.train, lr=base.train.lr),
            heads=base.heads,
            env=dataclasses.replace(cfg.env, windy=base.env.windy),
        )
        == base
    )


def test_later_overrides_win_and_quick_comes_before_cli():
    cfg = load_config(WINDY, ["train.total_frames=777"], quick=True)
    assert cfg.train.total_frames == 777
    assert cfg.experiment.runs == 2  # from quick_overrides
    assert load_config(WINDY, ["seed=1", "seed=2"]).seed == 2


def test_layout_map_string_override_and_null():
    cfg = load_config(WINDY, ["env.windy.layout=middle_exits", "env.windy.horizon=null"])
    assert cfg.env.windy.layout == "middle_exits" and cfg.env.windy.horizon is None


@pytest.mark.parametrize(
    "override, parts",
    [
        ("train.lrr=0.01", ["'train.lrr'", "override", "did you mean 'lr'", "batch_size"]),
        ("trian.lr=0.01", ["'trian'", "did you mean 'train'"]),
        ("train.lr=abc", ["'train.lr'", "abc", "Float"]),
        ("seed=1.5", ["'seed'", "Integer"]),
        ("train.double_q=maybe", ["'train.double_q'"]),
        ("heads.hidden=[a]", ["'heads.hidden'", "['a'] could not be converted to Integer"]),
        ("train.lr", ["key.sub=value"]),
        ("+train.new=1", ["key.sub=value"]),
    ],
)
def test_bad_override_is_a_one_line_error_naming_it(override, parts):
    _raises_one_line(parts, load_config, WINDY, [override])


def test_apply_overrides_on_a_config_object():
    cfg = apply_overrides(Config(), ["family=wargus", "eval.test=nominal"])
    assert cfg.family == "wargus" and cfg.eval.test == "nominal"
    _raises_one_line(["'eval.tset'"], apply_overrides, cfg, ["eval.tset=x"])


def test_typo_in_quick_overrides_fails_even_without_quick(tmp_path: Path):
    p = _write(tmp_path, "experiment:\n  quick_overrides: ['train.total_frame=10']\n")
    _raises_one_line(["'train.total_frame'"], load_config, p)


# ---------------------------------------------------------------- values


@pytest.mark.parametrize(
    "override, parts",
    [
        ("family=atari", ["family must be one of [", "'taxi', 'wargus', 'windy'", "'atari'"]),
        ("train.switching=hybrid", ["train.switching='hybrid'", "was removed", "one allowed"]),
        ("train.mu_bar=eps", ["train.mu_bar must be one of ['greedy', 'softmax']"]),
        ("train.target_update=polyak", ["train.target_update must be one of ['hard', 'soft']"]),
        (
            "env.windy.obs_encoding=pixels",
            [
                "env.windy.obs_encoding must be one of ['coords_patch', 'exits_patch', 'fourier_patch', 'onehot', 'rowcol_patch']"
            ],
        ),
        ("env.instances=east", ["env.instances must be one of", "'south'"]),
        ("eval.method=random", ["eval.method must be one of", "'interruption'"]),
        ("eval.test=west", ["eval.test must be one of"]),
        ("heads.activation=sigmoid", ["heads.activation must be one of", "'relu'"]),
        (
            "env.windy.layout=tiny",
            ["env.windy.layout must be one of", "'middle_exits'", "'generated'"],
        ),
        ("device=gpu", ["device must be a torch device"]),
        (
            "collector.backend=dask",
            ["collector.backend must be one of ['process', 'ray']", "'dask'"],
        ),
        ("collector.ray_address=auto", ["collector.ray_address is for collector.backend=ray"]),
    ],
)
def test_bad_choice_names_field_and_allowed_values(override, parts):
    _raises_one_line(parts, load_config, WINDY, [override])


@pytest.mark.parametrize(
    "override, key",
    [
        ("train.gamma=1.0", "train.gamma"),  # [0, 1): gamma = 1 never converges (issue 44)
        ("train.gamma=1.5", "train.gamma"),
        ("train.lr=0", "train.lr"),
        ("train.max_value_expectile=1.0", "train.max_value_expectile"),
        ("train.buffer_size=10", "train.buffer_size"),
        ("env.num_envs=0", "env.num_envs"),
        ("heads.hidden=[64,0]", "heads.hidden[1]"),
        ("train.max_grad_norm=0", "train.max_grad_norm"),
    ],
)
def test_out_of_range_value_names_the_field(override, key):
    _raises_one_line([key], load_config, WINDY, [override])


@pytest.mark.parametrize(
    "override, parts",
    [
        ("env.wargus.hit_prob=1.5", ["env.wargus.hit_prob", "[0, 1]"]),
        ("env.wargus.patrol_speed=-0.1", ["env.wargus.patrol_speed"]),
        ("env.wargus.shoot_range=8", ["env.wargus.shoot_range", "[0, 7]"]),
        ("env.wargus.size=2", ["env.wargus.size"]),
        ("env.instances=south", ["env.instances must be one of", "'nominal'"]),
        ("eval.test=south", ["eval.test must be one of", "'nominal'"]),
    ],
)
def test_wargus_values_are_checked_by_the_family_rules(override, parts):
    _raises_one_line(parts, load_config, CONFIG_DIR / "wargus.yaml", [override])


def test_only_the_chosen_family_keys_are_validated():
    assert load_config(CONFIG_DIR / "wargus.yaml").eval.test == "nominal"
    # a family's own keys exist for that family only: a windy config has no env.wargus, a Wargus
    # config no env.windy (nor the windy keys' old env.* spelling)
    _raises_one_line(["env.wargus"], load_config, WINDY, ["env.wargus.shoot_range=8"])
    wargus = CONFIG_DIR / "wargus.yaml"
    _raises_one_line(["env.windy"], load_config, wargus, ["env.windy.obs_encoding=x"])
    _raises_one_line(
        ["env.obs_encoding", "windy", "'wargus'"], load_config, wargus, ["env.obs_encoding=x"]
    )


def test_old_windy_spellings_migrate_with_one_deprecation_line(tmp_path):
    """Configs, checkpoints and overrides written before env.windy: the windy keys at env.* move
    to env.windy.* (a FutureWarning naming the move); another family's copy of them, and
    env.wargus in a windy config, are dropped (never read)."""
    new = load_config(WINDY, ["env.windy.layout=middle_exits", "env.windy.horizon=50"])
    with pytest.warns(FutureWarning, match="env.windy.layout"):
        old = load_config(WINDY, ["env.layout=middle_exits", "env.horizon=50"])
    assert old == new
    data = config_to_dict(new)
    data["env"] = {**{k: v for k, v in data["env"].items() if k != "windy"}, **data["env"]["windy"]}
    data["env"]["wargus"] = {"size": 16}
    with pytest.warns(FutureWarning, match="env.layout and the other windy keys are now env.windy"):
        assert config_from_dict(data, "an old checkpoint") == new
    taxi = config_to_dict(load_config(CONFIG_DIR / "taxi.yaml"))
    taxi["env"]["layout"] = "default"
    with pytest.warns(FutureWarning, match="windy keys at env.* \\(layout\\) are dropped"):
        assert config_from_dict(taxi, "an old checkpoint") == load_config(CONFIG_DIR / "taxi.yaml")


def test_the_experiments_keys_are_their_familys():
    """Figure 2's and Figure 4's keys are declared by the family that owns the experiment and read
    at the same paths (``experiment.trials``); another family's config refuses them with the
    unknown-key line; a config built in code gets its family's defaults (and pickles)."""
    import pickle

    core = {f.name for f in dataclasses.fields(ExperimentConfig)}
    assert core == {"runs", "quick_overrides"}
    assert "composed_reward" not in {f.name for f in dataclasses.fields(TrainConfig)}
    wargus = load_config(CONFIG_DIR / "wargus.yaml", ["experiment.trials=7"])
    assert isinstance(wargus.experiment, Fig4Config) and wargus.experiment.trials == 7
    windy = load_config(WINDY, ["experiment.episodes_per_run=9"])
    assert isinstance(windy.experiment, Fig2Config) and windy.experiment.episodes_per_run == 9
    _raises_one_line(
        ["unknown config key 'experiment.trials'", "runs, quick_overrides, episodes_per_run"],
        load_config,
        WINDY,
        ["experiment.trials=3"],
    )
    _raises_one_line(
        ["unknown config key 'experiment.episodes_per_run'"],
        load_config,
        CONFIG_DIR / "taxi.yaml",
        ["experiment.episodes_per_run=3"],
    )
    _raises_one_line(["experiment.trials must be in [1,"], load_config, CONFIG_DIR / "wargus.yaml",
                     ["experiment.trials=0"])  # fmt: skip
    plain = Config(family="wargus", experiment=ExperimentConfig(runs=2))
    assert (plain.experiment.runs, plain.experiment.trials) == (2, 500)
    assert pickle.loads(pickle.dumps(plain)) == plain
    assert config_to_dict(plain)["experiment"]["trials"] == 500
    assert Config().experiment.episodes_per_run == 10_000
    taxi = apply_overrides(windy, ["family=taxi", "env.instances=train", "eval.test=train"])
    assert (
        type(taxi.experiment) is ExperimentConfig and taxi.experiment.runs == windy.experiment.runs
    )
    # a loaded config's sections are its family's: replace() cannot switch family (one line)
    _raises_one_line(["a windy config does not become a taxi one", "apply_overrides"],
                     dataclasses.replace, windy, family="taxi")  # fmt: skip


def test_train_composed_reward_migrates_to_env_wargus_with_one_deprecation_line():
    """``train.composed_reward`` is Wargus's own key now, ``env.wargus.composed_reward``: the old
    override, and an old config holding it, load with one deprecation line and reach the
    subtasks; another family's old config drops it (never read), with Figure 4's keys."""
    from taskvar_torch.contract import family

    new = load_config(CONFIG_DIR / "wargus.yaml", ["env.wargus.composed_reward=sum"])
    with pytest.warns(FutureWarning, match="use env.wargus.composed_reward=sum") as rec:
        old = load_config(CONFIG_DIR / "wargus.yaml", ["train.composed_reward=sum"])
    assert len([w for w in rec if issubclass(w.category, FutureWarning)]) == 1
    assert old == new and old.env.wargus.composed_reward == "sum"
    subtasks = family("wargus").subtasks(old, None)
    assert isinstance(subtasks, WargusSubtasks) and subtasks.composed_reward == "sum"
    data = config_to_dict(new)
    del data["env"]["wargus"]["composed_reward"]
    data["train"]["composed_reward"] = "sum"
    with pytest.warns(FutureWarning, match="train.composed_reward is now env.wargus"):
        assert config_from_dict(data, "an old checkpoint") == new
    _raises_one_line(["env.wargus.composed_reward must be one of ['env', 'sum']"], load_config,
                     CONFIG_DIR / "wargus.yaml", ["env.wargus.composed_reward=mean"])  # fmt: skip
    _raises_one_line(["train.composed_reward is a wargus key", "'windy'"], load_config, WINDY,
                     ["train.composed_reward=sum"])  # fmt: skip
    windy = config_to_dict(load_config(WINDY))
    windy["train"]["composed_reward"] = "env"
    windy["experiment"].update(trials=500, test_episodes_per_trial=5, baselines=[])
    with pytest.warns(FutureWarning) as rec:
        assert config_from_dict(windy, "an old checkpoint") == load_config(WINDY)
    (line,) = [str(w.message) for w in rec if issubclass(w.category, FutureWarning)]
    assert "wargus keys at train.* (composed_reward) are dropped" in line
    assert "wargus-fig4 keys at experiment.* (trials, test_episodes_per_trial, baselines)" in line


def test_removed_keys_load_with_one_deprecation_line(tmp_path):
    """``train.switching`` (one allowed value, intra) is gone: an old config file, a checkpoint's
    config and an override holding it load without it, each with one FutureWarning; another value
    is a one-line error; an old checkpoint's config differs in nothing from its migration (so it
    resumes)."""
    from taskvar_torch.checkpoint import config_differences

    new = load_config(WINDY)
    text = WINDY.read_text()
    assert text.count("\n  mu_bar: greedy\n") == 1
    old_file = _write(
        tmp_path, text.replace("\n  mu_bar: greedy\n", "\n  switching: intra\n  mu_bar: greedy\n")
    )
    with pytest.warns(
        FutureWarning, match=r"train.switching is dropped \(it had one allowed"
    ) as rec:
        assert load_config(old_file) == new
    assert len([w for w in rec if issubclass(w.category, FutureWarning)]) == 1
    data = config_to_dict(new)
    data["train"]["switching"] = "intra"
    with pytest.warns(FutureWarning, match="train.switching is dropped"):
        assert config_from_dict(data, "an old checkpoint") == new
    with pytest.warns(FutureWarning, match="train.switching is deprecated"):
        assert load_config(WINDY, ["train.switching=intra"]) == new
    assert config_differences(data, new) == []
    bad = {**data, "train": {**data["train"], "switching": "smdp"}}
    _raises_one_line(["train.switching='smdp'", "was removed"], config_from_dict, bad)


def test_generator_keys_need_layout_generated():
    _raises_one_line(["env.windy.height", "generated"], load_config, WINDY, ["env.windy.height=9"])
    _raises_one_line(
        ["env.windy.width is required"],
        load_config,
        WINDY,
        ["env.windy.layout=generated", "env.windy.height=9"],
    )
    _raises_one_line(
        ["num_exits"],
        load_config,
        WINDY,
        [
            "env.windy.layout=generated",
            "env.windy.height=9",
            "env.windy.width=9",
            "env.windy.num_exits=1",
        ],
    )
    cfg = load_config(
        WINDY,
        [
            "env.windy.layout=generated",
            "env.windy.height=7",
            "env.windy.width=9",
            "env.windy.num_exits=3",
        ],
    )
    assert windy_layout(cfg.env.windy).num_exits == 3


def test_map_string_layout_in_yaml(tmp_path: Path):
    text = "env:\n  layout: |\n    S W . G\n    S . # G\n    S W . G\n"
    cfg = load_config(_write(tmp_path, text))
    assert windy_layout(cfg.env.windy).rows == ("SW.G", "S.#G", "SW.G")
    bad = "env:\n  layout: |\n    S W . G\n    S . #\n"
    _raises_one_line(["env.windy.layout", "row 1"], load_config, _write(tmp_path, bad, "b.yaml"))


def test_windy_env_kwargs_refuses_wargus():
    _raises_one_line(["family='windy'"], windy_env_kwargs, Config(family="wargus"))


# ---------------------------------------------------------------- dict, yaml, dataclass


def test_dict_round_trip_is_plain_data_and_strict():
    cfg = load_config(CONFIG_DIR / "windy_large.yaml", ["train.max_grad_norm=null"])
    d = config_to_dict(cfg)
    assert json.loads(json.dumps(d)) == d  # only plain data
    assert isinstance(d["heads"]["hidden"], list)
    assert config_from_dict(d) == cfg
    d["train"]["lrr"] = 1.0
    _raises_one_line(["'train.lrr'", "checkpoint"], config_from_dict, d, source="checkpoint x.pt")
    _raises_one_line(["mapping"], config_from_dict, [1, 2])


def test_save_config_yaml_round_trips_and_leaves_no_temp_files(tmp_path: Path):
    cfg = load_config(CONFIG_DIR / "wargus_large.yaml", ["seed=7"])
    out = tmp_path / "config.yaml"
    save_config_yaml(cfg, out)
    save_config_yaml(cfg, out)  # overwrite
    assert load_config(out) == cfg
    assert [p.name for p in tmp_path.iterdir()] == ["config.yaml"]


def test_config_is_frozen_and_validated_on_construction():
    cfg = Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 3  # type: ignore[misc]
    with pytest.raises(ValueError, match="train.eps_start"):
        dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, eps_start=2.0))


@pytest.mark.parametrize(
    "cls",
    [
        *(Config, EnvConfig, WargusConfig, WargusSection, HeadsConfig, TrainConfig, EvalConfig),
        *(ExperimentConfig, Fig2Config, Fig4Config),
    ],
)
def test_every_field_has_a_help_docstring(cls):
    docs = field_docs(cls)
    missing = [f.name for f in dataclasses.fields(cls) if not docs.get(f.name)]
    assert not missing


def test_config_help_lists_dotted_keys_with_defaults():
    text = config_help()
    assert "train.lr (float, default 0.001): Adam learning rate." in text
    assert "env.wargus.sight (int, default 8)" in text
    assert "heads.hidden (tuple[int, ...], default [64, 64])" in text


def test_failed_config_write_keeps_previous_file(tmp_path: Path, monkeypatch):
    out = tmp_path / "config.yaml"
    save_config_yaml(Config(seed=1), out)
    before = out.read_bytes()

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("os.replace", fail)
    with pytest.raises(OSError, match="disk full"):
        save_config_yaml(Config(seed=2), out)
    monkeypatch.undo()
    assert out.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["config.yaml"]


@pytest.mark.slow
def test_scale_config_file_loads_strictly_and_quick_applies_its_overrides():
    """Against the YAML read on its own: the cases in order, their configs beside the file, and
    ``quick`` the file's ``quick_overrides`` (the full config keeping the file's values)."""
    import yaml

    raw = yaml.safe_load(SCALE_CONFIG.read_text())
    full = load_scale_config(SCALE_CONFIG)
    quick = load_scale_config(SCALE_CONFIG, quick=True)
    assert isinstance(full, ScaleConfig) and isinstance(quick, ScaleConfig)
    assert [c.name for c in full.cases] == [c["name"] for c in raw["cases"]]
    assert [Path(c.config) for c in full.cases] == [
        SCALE_CONFIG.parent / c["config"] for c in raw["cases"]
    ]
    plain = lambda v: list(v) if isinstance(v, tuple) else v  # noqa: E731
    for item in raw["quick_overrides"]:
        key, _, value = item.partition("=")
        assert plain(getattr(quick, key)) == yaml.safe_load(value), key
        if key in raw:
            assert plain(getattr(full, key)) == raw[key], key


def test_a_list_item_cannot_be_set_alone():
    _raises_one_line(
        ["'heads.hidden.0'", "heads.hidden=[...]"], load_config, WINDY, ["heads.hidden.0=5"]
    )


def test_scale_config_errors_come_from_the_same_loader(tmp_path: Path):
    case = _write(tmp_path, "cases:\n  - {name: a, config: windy.yaml, extra: 1}\n")
    _raises_one_line(
        ["'extra'", "allowed keys in ScaleCase: name, config, overrides"], load_scale_config, case
    )
    _raises_one_line(
        ["'totl_frames'", "did you mean 'total_frames'"],
        load_scale_config,
        SCALE_CONFIG,
        ["totl_frames=1"],
    )
    _raises_one_line(
        ["key=value", "total_frames="], load_scale_config, SCALE_CONFIG, ["total_frames"]
    )
    listed = _write(tmp_path, "- 1\n", "list.yaml")
    _raises_one_line(["must hold a mapping"], load_scale_config, listed)


def test_one_method_list_in_the_papers_order():
    assert METHODS == ("averaging", "options", "interruption", "hierarchy")
    assert fig2_metrics.METHODS == tuple(m for m in METHODS if m != "hierarchy")
    assert windy_fig2.EXACT_MAX_CELLS == EXACT_ORACLE_CELLS
