"""Property-based fuzz (Hypothesis) of every grammar a user types: ``key.sub=value`` overrides
(``load_config`` and ``apply_overrides``), config files (generated YAML text), ``--shift`` items
(``parse_shift`` then ``shift_points``) and ``--test`` names.

The property: every input is either accepted (a valid config, a list of test points) or refused
with a one-line ``ValueError``; no other exception, no traceback, no newline in the message. The
inputs are near-valid (the schema's own keys, the families' own instance fields and test names,
with random values and typos) and junk.

Loading a config costs ~0.1-0.2 s (OmegaConf builds the structured schema each time), so each
example of the slow properties carries several inputs; the cheap grammars run thousands of
examples. The examples are derandomised, so CI sees the same inputs every run; explore new ones
with ``TASKVAR_FUZZ=explore`` (random and 20x more examples).
"""

from __future__ import annotations

import copy
import dataclasses
import os
import tempfile
import typing
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from taskvar_torch.config import apply_overrides, config_schema, config_to_dict, load_config
from taskvar_torch.experiments.shift import parse_shift, shift_points
from taskvar_torch.families import family

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = ("windy", "wargus", "taxi")
CONFIGS = {name: ROOT / "configs" / f"{name}.yaml" for name in FAMILIES}

EXPLORE = os.environ.get("TASKVAR_FUZZ") == "explore"
settings.register_profile(
    "taskvar-fuzz",
    deadline=None,
    database=None,  # no .hypothesis/ folder in the work tree
    derandomize=not EXPLORE,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    print_blob=True,
)
FUZZ = settings.get_profile("taskvar-fuzz")


def examples(n: int) -> settings:
    return settings(FUZZ, max_examples=n * 20 if EXPLORE else n)


def one_line(call, *args, **kwargs):
    """``call(...)``'s result, or None for a one-line ValueError; anything else fails the test."""
    try:
        return call(*args, **kwargs)
    except ValueError as e:
        msg = str(e)
        assert msg.strip(), f"empty ValueError message from {args!r}"
        assert "\n" not in msg and "\r" not in msg, f"multi-line message: {msg!r}"
        assert "Traceback" not in msg, msg
        return None


# --------------------------------------------------------------------------------------------
# the schema's own keys


def _leaves(cls: type, prefix: str = "") -> list[tuple[str, type]]:
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t):
            out += _leaves(t, f"{prefix}{f.name}.")
        else:
            out.append((f"{prefix}{f.name}", t))
    return out


KEYS = {name: [k for k, _ in _leaves(config_schema(name))] for name in FAMILIES}
ALL_KEYS = sorted({k for keys in KEYS.values() for k in keys})
TREES = {name: config_to_dict(load_config(CONFIGS[name])) for name in FAMILIES}
SECTIONS = sorted({k.rsplit(".", 1)[0] for k in ALL_KEYS if "." in k})


@pytest.fixture(scope="module")
def base_configs():
    return {name: load_config(CONFIGS[name]) for name in FAMILIES}


# --------------------------------------------------------------------------------------------
# strategies

JUNK_CHARS = st.characters(codec="utf-8", exclude_categories=("Cs",))
PUNCT = "=.,:[]{}'\"\\$%&*!|>#@`~+- \t\n?"


def typo(word: str) -> st.SearchStrategy[str]:
    """``word`` with one character dropped, doubled, replaced or the case changed."""
    if not word:
        return st.just(word)
    return st.one_of(
        st.integers(0, len(word) - 1).map(lambda i: word[:i] + word[i + 1 :]),
        st.integers(0, len(word) - 1).map(lambda i: word[:i] + word[i] + word[i:]),
        st.tuples(st.integers(0, len(word) - 1), st.sampled_from("aex_.0[ ")).map(
            lambda t: word[: t[0]] + t[1] + word[t[0] + 1 :]
        ),
        st.just(word.upper()),
        st.just(word + "."),
        st.just("." + word),
        st.just(word + "[0]"),
        st.just(word + ".0"),
        st.just(word + ".x"),
    )


real_key = st.sampled_from(ALL_KEYS)
key = st.one_of(
    real_key,
    real_key,
    real_key.flatmap(typo),
    st.sampled_from(SECTIONS),  # a section given a value
    st.sampled_from(["family", "seed", "device", "", " ", "env.", ".env", "env..horizon"]),
    st.text(JUNK_CHARS, max_size=12),
)
number = st.one_of(
    st.integers(-(2**70), 2**70).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "1", "-1", "1e309", "-1e309", ".nan", ".inf", "-.inf", "1_000", "0x10"]),
    st.sampled_from(["0.5", "1e-3", "2.", "+3", "00", "1e400", "nan", "inf", "1/2", "3j"]),
)
yaml_word = st.sampled_from(
    [
        "true",
        "false",
        "null",
        "~",
        "???",
        "''",
        '""',
        "[]",
        "{}",
        "[1, 2]",
        "[64, 64]",
        "[[1]]",
        "[a, b]",
        "{a: 1}",
        "{hidden: [1]}",
        "${seed}",
        "${train.lr}",
        "${nope}",
        "${oc.env:HOME}",
        "${oc.env:NOPE_NOT_SET}",
        "${oc.decode:'[1,2]'}",
        "${",
        "}",
        "[",
        "{",
        "'",
        '"',
        "a: b",
        "- a",
        "&a",
        "*a",
        "!!python/object:os.system",
        "!!binary aGk=",
        "|",
        ">",
        "%",
        "@",
        "`",
        "#",
        "\\",
        "\\n",
        "2026-01-01",
        "12:30",
        "cpu",
        "cuda",
        "cuda:7",
        "mps",
        "meta",
        "windy",
        "wargus",
        "taxi",
        "corridor",
        "default",
        "generated",
        "relu",
        "onehot",
        "train",
        "south",
        "hard",
        "soft",
        "csv",
    ]
)
value = st.one_of(
    number,
    yaml_word,
    st.text(st.sampled_from(PUNCT + "ab01"), max_size=8),
    st.text(JUNK_CHARS, max_size=10),
    st.lists(number, max_size=3).map(lambda xs: "[" + ",".join(xs) + "]"),
)
override = st.one_of(
    st.builds(
        lambda k, sep, v: f"{k}{sep}{v}",
        key,
        st.sampled_from(["=", "=", "=", "==", " = ", ": ", ""]),
        value,
    ),
    st.builds(
        lambda p, k, v: f"{p}{k}={v}", st.sampled_from(["+", "~", "++", "-"]), real_key, value
    ),
    st.text(st.sampled_from(PUNCT + "abenvtrai"), max_size=16),
    st.text(JUNK_CHARS, max_size=16),
)
family_name = st.sampled_from(FAMILIES)


# --------------------------------------------------------------------------------------------
# overrides: load_config(file, overrides) and apply_overrides(cfg, overrides)


@pytest.mark.slow
@examples(30)
@given(family_name, st.lists(override, min_size=1, max_size=6), st.booleans())
def test_load_config_with_fuzzed_overrides_is_a_config_or_one_line(fam, overrides, quick):
    one_line(load_config, CONFIGS[fam], overrides, quick=quick)  # the first bad one is named


@pytest.mark.slow
@examples(60)
@given(family_name, st.lists(override, min_size=1, max_size=6))
def test_apply_overrides_with_fuzzed_overrides_is_a_config_or_one_line(
    base_configs, fam, overrides
):
    cfg = one_line(apply_overrides, base_configs[fam], overrides)
    if cfg is not None:
        assert one_line(apply_overrides, cfg, []) == cfg  # what was accepted rebuilds as itself


# --------------------------------------------------------------------------------------------
# config files: a family's own config with random leaves changed, keys dropped or added; junk


scalar = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**66), 2**66),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(JUNK_CHARS, max_size=8),
    yaml_word,
)
leaf_value = st.recursive(
    scalar,
    lambda inner: st.one_of(
        st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=4), inner, max_size=2)
    ),
    max_leaves=4,
)


def _set(tree: dict, dotted: str, value) -> None:
    parts = dotted.split(".")
    node = tree
    for p in parts[:-1]:
        if not isinstance(node.get(p), dict):
            node[p] = {}
        node = node[p]
    node[parts[-1]] = value


def _drop(tree: dict, dotted: str) -> None:
    parts = dotted.split(".")
    node = tree
    for p in parts[:-1]:
        node = node.get(p)
        if not isinstance(node, dict):
            return
    node.pop(parts[-1], None)


@st.composite
def config_text(draw) -> str:
    """YAML text: a family's config dict mutated (or not), dumped; or YAML-ish junk."""
    kind = draw(st.sampled_from(["mutated", "mutated", "mutated", "junk", "yaml-junk"]))
    if kind == "junk":
        return draw(st.text(st.sampled_from(PUNCT + "abenvy01:\n  -"), max_size=40))
    if kind == "yaml-junk":
        return yaml.safe_dump(draw(leaf_value), allow_unicode=True)
    fam = draw(family_name)
    tree = copy.deepcopy(TREES[fam])
    for _ in range(draw(st.integers(0, 4))):
        action = draw(st.sampled_from(["set", "set", "drop", "typo"]))
        k = draw(st.sampled_from(KEYS[fam]))
        if action == "set":
            _set(tree, k, draw(leaf_value))
        elif action == "drop":
            _drop(tree, k)
        else:
            _set(tree, draw(typo(k)), draw(leaf_value))
    return yaml.safe_dump(tree, allow_unicode=True, sort_keys=draw(st.booleans()))


@pytest.mark.slow
@examples(50)
@given(config_text())
def test_fuzzed_config_files_are_a_config_or_one_line(text):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "config.yaml"
        path.write_text(text, encoding="utf-8")
        cfg = one_line(load_config, path)
    if cfg is not None:
        assert config_to_dict(one_line(apply_overrides, cfg, [])) == config_to_dict(cfg)


# --------------------------------------------------------------------------------------------
# --shift and --test


def _instance_field_names(fam: str, cfg) -> list[str]:
    f = family(cfg)
    names = set(f.shift_aliases)
    for dist in f.tests.values():
        if f.instance_fields is not None:
            names |= set(f.instance_fields(dist.instances))
    return sorted(names)


SHIFT_KEYS = sorted({k for k in ALL_KEYS if k.startswith("env.")})


@st.composite
def shift_item(draw, fam: str, fields: list[str]) -> str:
    k = draw(
        st.one_of(
            st.sampled_from(SHIFT_KEYS),
            st.sampled_from(["env.instances." + f for f in fields] or ["env.instances.x"]),
            st.just("env.instances"),
            st.sampled_from(SHIFT_KEYS).flatmap(typo),
            st.sampled_from(["env.instances." + f for f in fields] or ["env.x"]).flatmap(typo),
            st.sampled_from(["train.lr", "seed", "env", "", "env.", "instances.p"]),
            st.text(JUNK_CHARS, max_size=10),
        )
    )
    instance_words = [
        "north",
        "south",
        "north+south",
        "east",
        "0+1+2",
        "1+",
        "+",
        "a+b",
        "cycle",
        "uniform",
    ]
    v = st.one_of(value, st.sampled_from(instance_words), st.sampled_from(["0.2", "0.5", "1", "0"]))
    vals = draw(st.lists(v, min_size=1, max_size=3))
    sep = draw(st.sampled_from(["=", "=", "=", "", "=="]))
    return f"{k}{sep}{','.join(vals)}"


@st.composite
def shift_case(draw):
    fam = draw(family_name)
    return fam, draw(st.lists(st.just(fam).flatmap(lambda f: shift_item(f, FIELDS[f])), max_size=3))


FIELDS: dict[str, list[str]] = {}


@pytest.fixture(scope="module", autouse=True)
def _fields(base_configs):
    for name, cfg in base_configs.items():
        FIELDS[name] = _instance_field_names(name, cfg)


test_names = st.one_of(
    st.none(),
    st.sampled_from(
        sorted({n for f in FAMILIES for n in ("train", "south", "nominal", "storm", "dry", "calm")})
    ),
    st.text(JUNK_CHARS, max_size=10),
)


@examples(700)
@given(
    st.one_of(st.text(JUNK_CHARS, max_size=30), shift_item("windy", ["p", "p_low", "directions"]))
)
@pytest.mark.slow
def test_parse_shift_is_a_shift_or_one_line(item):
    s = one_line(parse_shift, item)
    if s is not None:
        assert s.key.startswith("env.") and s.values and all(s.values)


@pytest.mark.slow
@examples(1500)
@given(family_name, st.one_of(test_names, st.sampled_from(["train", "south"]).flatmap(typo)))
def test_test_names_are_points_or_one_line(base_configs, fam, name):
    points = one_line(shift_points, base_configs[fam], name, [])
    if points is not None:
        assert len(points) == 1 and name in (None, *family(base_configs[fam]).tests)


@pytest.mark.slow
@examples(300)
@given(shift_case(), test_names)
def test_shift_points_are_points_or_one_line(base_configs, case, test):
    fam, items = case
    shifts = [one_line(parse_shift, i) for i in items]
    if any(s is None for s in shifts):
        return
    points = one_line(shift_points, base_configs[fam], test, shifts)
    if points is not None:
        assert len(points) == max([len(s.values) for s in shifts] + [1])
