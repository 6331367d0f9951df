"""The family contract and registry (docs/families.md#the-contract).

A family is a distribution over MDPs sharing states and actions (paper §2): its batched env, its
options, its named instance and test distributions, and what the heads, the oracle and the
experiments can use of it. Code reads the registry (:func:`family`), never a family's name;
families come from :func:`register_family` or the ``taskvar_torch.families`` entry-point group
(the built-ins too, :data:`BUILTIN`). This module imports only :mod:`taskvar_torch.rng`, so every
layer may read it.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import inspect
import math
import os
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from torchrl.envs import EnvBase

from taskvar_torch import rng

if TYPE_CHECKING:
    from taskvar_torch.subtasks.base import Subtasks

Config = Any
"""A :class:`taskvar_torch.config.Config` (not imported: the config package reads this registry,
never the reverse)."""
EnvConfig = Any
"""Its ``env`` section, :class:`taskvar_torch.config.EnvConfig`."""

ENTRY_POINT_GROUP = "taskvar_torch.families"
"""The entry-point group an installed package registers its families under (docs/families.md)."""
BUILTIN = {
    "windy": "taskvar_torch.families.windy.family:family",
    "wargus": "taskvar_torch.families.wargus.family:family",
    "taxi": "taskvar_torch.families.taxi.family:family",
    "minigrid": "taskvar_torch.families.minigrid.family:family",
}
"""The package's own families (``families/<name>/``), loaded through the same door as an installed
package's entry points (and listed in its ``pyproject.toml``); another family of one of these
names is refused."""
HELDOUT_SEED = 7_000_000
"""First seed of the sealed held-out range ``[HELDOUT_SEED, HELDOUT_SEED + HELDOUT_SIZE)``
(docs/claims.md): no config, doc, test or tuning script names a seed in it
(``tests/test_heldout.py`` checks), so no design choice was ever made on its episodes. Windy and
Taxi play their test distribution under env seed ``HELDOUT_SEED + run`` drawn per training seed
(:func:`sealed_episode_seed`); Wargus plays the instance seeds of the range."""
HELDOUT_SIZE = 300
"""Seeds in the sealed range: Wargus's held-out instances, and the most held-out runs."""
HELDOUT_SEEDS = tuple(range(HELDOUT_SEED, HELDOUT_SEED + HELDOUT_SIZE))
"""The sealed held-out seeds, in order (Wargus's held-out instance seeds)."""


def sealed_episode_seed(sealed: int, training_seed: int) -> int:
    """Env seed under which training seed ``training_seed``'s bundle plays sealed test seed
    ``sealed`` (docs/evaluation.md): ``rng.sub_env_key(sealed, training_seed)``, distinct per
    training seed, the same for every method of a bundle (paired)."""
    return int(
        rng.sub_env_key(rng.check_seed(sealed, "sealed seed"), rng.check_seed(training_seed))
    )


@dataclass(frozen=True)
class PatchLayout:
    """Where the local patch sits in an observation (``Family.conv_patch``, ``heads.network=conv``):
    ``coords_dim`` values, then a ``(channels, size, size)`` patch, channel-major then row-major
    (windy's ``coords_patch``: 2 coordinates, 3 channels wall/wind/goal, ``size = 2r + 1``)."""

    coords_dim: int
    channels: int
    size: int

    @property
    def obs_dim(self) -> int:
        return self.coords_dim + self.channels * self.size * self.size


@dataclass(frozen=True)
class TestDistribution:
    """A named test distribution of a family (``taskvar eval --test NAME``).

    Attributes:
        description: what it shifts, in one line (docs/evaluation.md).
        instances: a named instance distribution or its fields (a dict).
        overrides: ``env`` config overrides (``key=value``), validated like a config.
        seed: a sealed test seed (``HELDOUT_SEED``) played per training seed
            (:func:`sealed_episode_seed`; another ``--seed`` is refused); ``None``: the
            evaluation's.
    """

    __test__ = False  # not a pytest test class

    description: str
    instances: Any = "train"
    overrides: tuple[str, ...] = ()
    seed: int | None = None


@dataclass(frozen=True)
class Experiment:
    """One experiment (``taskvar experiment NAME``): its module and entry points there; a family
    declares its figure experiment (``Family.experiment``).

    Attributes:
        name: ``taskvar experiment NAME`` and ``metrics.json``'s ``"experiment"``.
        module: dotted module holding the functions below.
        run: ``run(cfg, out_dir, ...) -> metrics``.
        plot: ``plot(out_dir) -> [png paths]`` (from the results folder alone).
        default_config: ``default_config() -> Path`` of its YAML config.
        schema: the config dataclass its YAML follows (``Config`` or ``ScaleConfig``).
        loader: ``loader(path, overrides, quick=...) -> config`` for a schema other than ``Config``.
        description: one line for ``--help``.
        config_class: its own keys, a frozen dataclass read flat under ``experiment.*`` in its
            family's configs only; ``None``: none.
        refusals: option of ``taskvar experiment`` -> the one-line reason it is not taken.
    """

    name: str
    module: str
    run: str
    plot: str = "plot_results"
    default_config: str = "default_config_path"
    schema: str = "Config"
    loader: str | None = None
    description: str = ""
    config_class: type | None = None
    refusals: tuple[tuple[str, str], ...] = ()

    def load(self) -> ModuleType:
        """The experiment's module (imported now)."""
        return importlib.import_module(self.module)

    def function(self, attr: str) -> Callable[..., Any]:
        """``run``, ``plot`` or ``default_config`` as a callable."""
        return getattr(self.load(), getattr(self, attr))

    def takes(self, option: str) -> bool:
        """Whether ``run`` takes the keyword ``option`` (e.g. ``workers``: wargus-fig4 only)."""
        return option in inspect.signature(self.function("run")).parameters

    def refuse(self, option: str, flag: str | None = None) -> None:
        """A one-line ``ValueError`` unless ``run`` takes ``option`` (named ``flag`` to the
        user, e.g. ``--workers``): the experiment's own reason where it gives one."""
        if self.takes(option):
            return
        reason = dict(self.refusals).get(option)
        raise ValueError(reason or f"{flag or option} is not an option of {self.name}")

    def call(self, cfg: Any, out_dir: str | os.PathLike, **options: Any) -> dict[str, Any]:
        """Run the experiment with ``options``; one it does not take is a one-line
        ``ValueError`` (:meth:`refuse`), never dropped."""
        for k in options:
            self.refuse(k)
        return self.function("run")(cfg, out_dir, **options)

    def default_config_path(self) -> Path:
        return self.function("default_config")()

    def plot_results(self, out_dir: str | os.PathLike) -> list[Path]:
        return self.function("plot")(out_dir)


@dataclass(frozen=True, kw_only=True)
class Family:
    """One task family: how to build its env and options from a config, and what it supports.

    The first five attributes are required; the rest are optional (``None``: not offered, and a
    command that needs it says so in one line). Their meanings in full, and the contract the env
    and subtasks honour: docs/families.md#the-contract.

    Attributes:
        name: the config's ``family`` value.
        env_class: the batched TorchRL env (a ``BatchedFamilyEnv``); its constructor takes
            ``num_envs``, ``seed``, ``instances``, ``index_offset``, ``noise_seed`` and
            ``validate_actions`` besides ``env_kwargs``.
        env_kwargs: config -> keyword arguments of ``env_class`` for the training env.
        subtasks: (config, env) -> the family's options (a :class:`Subtasks`).
        instance_names: the named instance distributions (must include ``train``).
        config_class: own env keys, a frozen dataclass read strictly under ``env.<name>``.
        validate: extra checks of a config of this family (one-line ``ValueError``).
        tests: the named test distributions (``taskvar eval --test``), the first the default.
        instance_fields: an instance distribution -> its fields as a dict (``--shift``).
        make_instances: fields -> an instance distribution (one-line ``ValueError``).
        shift_aliases: extra ``env.instances.FIELD`` names ``make_instances`` accepts.
        instance_dim: features of the hidden instance, computed by ``instance_features``.
        instance_features: transitions -> ``(B, instance_dim)`` features of ``("instance", ...)``.
        informed_features: config -> ``(dim, features)`` for the ``informed`` baseline;
            ``None``: ``(instance_dim, instance_features)``.
        oracle: config -> an :class:`~taskvar_torch.oracle.protocol.ExactOracle`, or ``None``.
        oracle_summary: (heads, config) -> lines printed after ``taskvar train``.
        averaging_optimum: config -> the exact mean-MDP averaging policy ``(cells,)``.
        head_report: (config, heads, with_max_value) -> every head against exact values.
        experiment: the family's figure experiment (an :class:`Experiment`).
        grid_side: config -> the grid's side length.
        cells: config -> the number of positions of the agent.
        observation: config -> the observation encoding's name.
        observation_size: config -> the observation's length without building the env; ``None``:
            read from a one-environment env.
        conv_patch: config -> the observation's patch layout (``heads.network=conv``).
        option_inputs: per-option input features (``heads.option_inputs=subtask``).
        description: one line for listings.
        gym_ids: Gymnasium id -> ``("module:Class", kwargs)``, registered lazily.
        legacy_env_keys: keys of ``config_class`` older configs held elsewhere (``KEY`` at
            ``env.KEY`` or a dotted path), moved with a deprecation line.
        legacy_section: older configs held ``env.<name>`` whatever their family; dropped elsewhere
            with a deprecation line.
        resumable: ``env.state_dict()`` continues every episode; ``False``: ``--resume`` refuses
            and ``check_family`` skips the resume check.
        failed_below: a seed whose mean return per episode is below this failed
            (docs/report.md#failed-seeds); chosen from the reward alone. ``None``: no rule.
    """

    name: str
    env_class: type[EnvBase]
    env_kwargs: Callable[[Config], dict[str, Any]]
    subtasks: Callable[[Config, EnvBase], Subtasks]
    instance_names: tuple[str, ...]
    config_class: type | None = None
    validate: Callable[[Config], None] | None = None
    tests: dict[str, TestDistribution] = dataclasses.field(default_factory=dict)
    instance_fields: Callable[[Any], dict[str, Any]] | None = None
    make_instances: Callable[[dict[str, Any]], Any] | None = None
    shift_aliases: tuple[str, ...] = ()
    instance_dim: int | None = None
    instance_features: Callable[[Any], Any] | None = None
    informed_features: Callable[[Config], tuple[int, Callable[[Any], Any]]] | None = None
    oracle: Callable[[Config], Any] | None = None
    oracle_summary: Callable[[Any, Config], list[str]] | None = None
    averaging_optimum: Callable[[Config], Any] | None = None
    head_report: Callable[..., dict[str, Any]] | None = None
    experiment: Experiment | None = None
    grid_side: Callable[[Config], int] | None = None
    cells: Callable[[Config], int] | None = None
    observation: Callable[[Config], str] | None = None
    observation_size: Callable[[Config], int] | None = None
    conv_patch: Callable[[Config], PatchLayout] | None = None
    option_inputs: bool = False
    description: str = ""
    gym_ids: Mapping[str, tuple[str, dict[str, Any]]] = dataclasses.field(default_factory=dict)
    legacy_env_keys: tuple[str, ...] = ()
    legacy_section: bool = False
    resumable: bool = True
    failed_below: float | None = None

    @property
    def exact_oracle(self) -> bool:
        """Whether the family brings an exact oracle (``oracle``)."""
        return self.oracle is not None

    def env_config(self, cfg: Config) -> Any:
        """The family's own keys of ``cfg`` (``cfg.env.<name>``; defaults when the config was
        built without them); ``None`` for a family without ``config_class``."""
        if self.config_class is None:
            return None
        section = getattr(cfg.env, self.name, None)
        return self.config_class() if section is None else section

    def make_env(
        self,
        cfg: Config,
        num_envs: int | None = None,
        *,
        seed: int | None = None,
        index_offset: int = 0,
        instances: Any = None,
        noise_seed: int | None = None,
        validate_actions: bool | None = None,
    ) -> EnvBase:
        """The family's batched env of ``cfg`` (no transforms); ``None`` keeps the config's value.
        ``index_offset``: global index of sub-env 0 in the keyed streams; ``noise_seed``: keys the
        per-step noise apart from the instances.
        """
        kw = self.env_kwargs(cfg)
        kw["index_offset"] = int(index_offset)
        if num_envs is not None:
            kw["num_envs"] = int(num_envs)
        if seed is not None:
            kw["seed"] = int(seed)
        if instances is not None:
            kw["instances"] = instances
        if noise_seed is not None:
            kw["noise_seed"] = int(noise_seed)
        if validate_actions is not None:
            kw["validate_actions"] = bool(validate_actions)
        return self.env_class(**kw)

    def require(self, cfg: Config, what: str) -> None:
        """Refuse a config of another family for ``what`` (an experiment or command)."""
        if cfg.family != self.name:
            raise ValueError(f"{what} needs family={self.name!r}, got family={cfg.family!r}")

    def needs(self, capability: str, what: str) -> Any:
        """The optional attribute ``capability``, or a one-line ``ValueError`` saying that
        ``what`` needs it and this family does not bring it."""
        value = getattr(self, capability)
        if value is None or value == {}:
            raise ValueError(
                f"{what} needs a family with {capability!r}; family {self.name!r} has none "
                "(docs/families.md)"
            )
        return value


# --------------------------------------------------------------------------------------------
# the registry


def _entry_points() -> list[importlib.metadata.EntryPoint]:
    """The built-in families (:data:`BUILTIN`, first) and every installed distribution's
    ``taskvar_torch.families`` entry points, every copy of the metadata read (a stale
    ``*.egg-info`` cannot hide them).
    """
    out = [
        importlib.metadata.EntryPoint(name=name, value=value, group=ENTRY_POINT_GROUP)
        for name, value in BUILTIN.items()
    ]
    seen = {(ep.name, ep.value) for ep in out}
    for dist in importlib.metadata.distributions():
        for ep in dist.entry_points:
            if ep.group == ENTRY_POINT_GROUP and (ep.name, ep.value) not in seen:
                seen.add((ep.name, ep.value))
                out.append(ep)
    return out


class _Registry(Mapping):
    """Every family by name, registered or from entry points. An entry point is imported only when
    its family is asked for (a broken plugin cannot take down a command that does not use it);
    iterating imports nothing; one that fails to load is one warning, and listed in :attr:`broken`.
    """

    def __init__(self) -> None:
        self._families: dict[str, Family] = {}
        self._entry_points_loaded = False
        """Whether the installed metadata was read into ``_pending`` (reset to read it again)."""
        self._pending: dict[str, importlib.metadata.EntryPoint] = {}
        self.broken: dict[str, str] = {}
        """Entry points that failed to load: name -> the one-line reason (warned once)."""

    def _read_entry_points(self) -> dict[str, importlib.metadata.EntryPoint]:
        """The entry points by name (the first of a name wins), read once; none imported."""
        if not self._entry_points_loaded:
            self._entry_points_loaded = True
            self._pending = {}
            for ep in _entry_points():
                self._pending.setdefault(ep.name, ep)
        return self._pending

    def installed(self, name: str) -> bool:
        """Whether a new process finds family ``name`` by itself: built in, or an installed
        package's entry point (not one :func:`register_family` added in this process only)."""
        return name in BUILTIN or name in self._read_entry_points()

    def entry_points(self) -> dict[str, str]:
        """Every entry-point family not imported yet: name -> ``module:attr`` (from metadata)."""
        return {
            name: ep.value
            for name, ep in self._read_entry_points().items()
            if name not in self._families and name not in self.broken
        }

    def _load(self, name: str) -> None:
        """Import the entry point of family ``name``, if any and not yet done; a failure of any
        kind (an exception, ``sys.exit``, ``KeyboardInterrupt`` raised on import, a wrong
        declaration) is a warning naming it and an entry in :attr:`broken`."""
        if name in self._families or name in self.broken:
            return
        ep = self._read_entry_points().get(name)
        if ep is None:
            return
        try:
            obj = ep.load()
            fam = obj if isinstance(obj, Family) else obj()
            if not isinstance(fam, Family):
                raise TypeError(f"it gives {type(fam).__name__}, not a Family")
            if fam.name != ep.name:
                raise ValueError(f"the entry point is named {ep.name!r}, its family {fam.name!r}")
            check_declaration(fam)
        except (Exception, SystemExit, KeyboardInterrupt) as e:  # not the command's failure
            if isinstance(e, KeyboardInterrupt) and hasattr(e, "signum"):
                raise  # SIGTERM, turned into an interrupt by the command: the command's to report
            reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            if isinstance(e, SystemExit):  # sys.exit() on import: not the command's exit
                reason = f"it called sys.exit({e.code!r}) on import"
            elif isinstance(e, KeyboardInterrupt):
                reason = "it raised KeyboardInterrupt on import"
            else:
                reason = f"{type(e).__name__}: {reason}"
            self.broken[ep.name] = f"entry point {ep.value!r}: {reason}"
            warnings.warn(
                f"taskvar_torch: family {ep.name!r} from {ep.value!r} could not be loaded: "
                f"{reason}",
                stacklevel=3,
            )
            return
        if fam.name not in self._families:  # registered while importing: that one stays
            self._families[fam.name] = fam
            register_gym_ids(fam)

    def loaded(self) -> dict[str, Family]:
        """The built-in families and those imported so far: what a pass over every family's
        declaration (renamed keys, messages) reads without importing an unused plugin."""
        for name in BUILTIN:
            self._load(name)
        return dict(self._families)

    def __getitem__(self, name: str) -> Family:
        if isinstance(name, str):
            self._load(name)
        return self._families[name]

    def __iter__(self) -> Iterator[str]:
        names = dict.fromkeys([*self._families, *self._read_entry_points()])
        return iter([n for n in names if n not in self.broken])

    def __len__(self) -> int:
        return len(list(iter(self)))

    def __contains__(self, name: object) -> bool:
        if isinstance(name, str):
            self._load(name)
        return name in self._families

    def values(self) -> list[Family]:  # type: ignore[override]
        """Every family, each entry point imported (a broken one warned about and left out)."""
        return [fam for _, fam in self.items()]

    def items(self) -> list[tuple[str, Family]]:  # type: ignore[override]
        """``(name, family)`` of every family, each entry point imported (a broken one left out)."""
        for name in list(self):
            self._load(name)
        return list(self._families.items())

    def __repr__(self) -> str:
        return f"FAMILIES({sorted(self)})"


FAMILIES = _Registry()
"""Every family, by its config name (a read-only mapping; add with :func:`register_family`)."""


def check_declaration(fam: Family) -> None:
    """What :func:`register_family` checks without building anything: one-line errors."""
    if not isinstance(fam.name, str) or not fam.name.isidentifier():
        raise ValueError(f"family name must be an identifier such as 'taxi', got {fam.name!r}")
    if not (isinstance(fam.env_class, type) and issubclass(fam.env_class, EnvBase)):
        raise ValueError(f"family {fam.name!r}: env_class must be a torchrl EnvBase subclass")
    for attr in ("env_kwargs", "subtasks"):
        if not callable(getattr(fam, attr)):
            raise ValueError(f"family {fam.name!r}: {attr} must be callable")
    if not fam.instance_names or not all(isinstance(n, str) for n in fam.instance_names):
        raise ValueError(f"family {fam.name!r}: instance_names must name at least one distribution")
    _check_keys_class(fam, fam.config_class, "config_class", f"env.{fam.name}.*")
    own = {f.name for f in dataclasses.fields(fam.config_class)} if fam.config_class else set()
    for old in fam.legacy_env_keys:
        parts = old.split(".") if isinstance(old, str) else [""]
        if len(parts) > 2 or not all(p.isidentifier() for p in parts) or parts[-1] not in own:
            raise ValueError(
                f"family {fam.name!r}: legacy_env_keys entries must be KEY or SECTION.KEY naming "
                f"a field of config_class ({sorted(own)}), got {old!r}"
            )
    if fam.experiment is not None and not isinstance(fam.experiment, Experiment):
        raise ValueError(
            f"family {fam.name!r}: experiment must be an Experiment (taskvar_torch.contract), "
            f"got {fam.experiment!r}"
        )
    if fam.experiment is not None:
        _check_keys_class(
            fam, fam.experiment.config_class, "experiment.config_class", "experiment.*"
        )
    if fam.informed_features is not None and not callable(fam.informed_features):
        raise ValueError(f"family {fam.name!r}: informed_features must be callable")
    if (fam.instance_dim is None) != (fam.instance_features is None):
        raise ValueError(
            f"family {fam.name!r}: instance_dim and instance_features go together (both or none)"
        )
    for env_id, spec in dict(fam.gym_ids).items():
        if not (
            isinstance(env_id, str)
            and isinstance(spec, tuple)
            and len(spec) == 2
            and isinstance(spec[0], str)
            and ":" in spec[0]
            and isinstance(spec[1], Mapping)
        ):
            raise ValueError(
                f"family {fam.name!r}: gym_ids[{env_id!r}] must be ('module:Class', kwargs)"
            )
    fb = fam.failed_below
    if fb is not None and (
        isinstance(fb, bool) or not isinstance(fb, int | float) or not math.isfinite(fb)
    ):
        raise ValueError(
            f"family {fam.name!r}: failed_below must be a finite number or None, got {fb!r}"
        )
    for name, dist in fam.tests.items():
        if not isinstance(dist, TestDistribution):
            raise ValueError(f"family {fam.name!r}: tests[{name!r}] must be a TestDistribution")


def _check_keys_class(fam: Family, cls: type | None, attr: str, where: str) -> None:
    """A family's own keys (``attr``, read at ``where``): ``None`` or a frozen dataclass that
    builds with its defaults; a one-line ``ValueError`` otherwise."""
    if cls is None:
        return
    params = getattr(cls, "__dataclass_params__", None)
    if params is None or not params.frozen:
        raise ValueError(f"family {fam.name!r}: {attr} must be a frozen dataclass ({where})")
    try:
        cls()
    except Exception as e:
        raise ValueError(
            f"family {fam.name!r}: {attr}() must build with its defaults: {e}"
        ) from None


def one_of(key: str, value: Any, allowed: tuple[str, ...]) -> None:
    """A family's validation helper: a one-line ``ValueError`` naming ``key`` and the allowed
    values unless ``value`` is one of ``allowed``."""
    if value not in allowed:
        raise ValueError(f"{key} must be one of {sorted(allowed)}, got {value!r}")


def register_family(fam: Family, *, replace: bool = False) -> Family:
    """Add ``fam`` to the registry (contract: :class:`Family`, docs/families.md) and return it;
    ``replace`` replaces an earlier family of that name (never a built-in one).

    Raises:
        ValueError: in one line, a declaration that breaks the contract, a built-in family's name,
            or a name already taken (without ``replace``).
    """
    if not isinstance(fam, Family):
        raise ValueError(f"register_family takes a Family, got {type(fam).__name__}")
    check_declaration(fam)
    existing = FAMILIES._families.get(fam.name)
    if existing is not None and existing is not fam:
        if fam.name in BUILTIN:
            raise ValueError(f"family {fam.name!r} is built in; choose another name")
        if not replace:
            raise ValueError(
                f"family {fam.name!r} is already registered; pass replace=True to replace it"
            )
    FAMILIES._families[fam.name] = fam
    register_gym_ids(fam)
    return fam


def register_gym_ids(fam: Family) -> None:
    """Register the family's Gymnasium ids (``Family.gym_ids``) not registered yet."""
    import gymnasium as gym

    for env_id, (entry_point, kwargs) in fam.gym_ids.items():
        if env_id not in gym.registry:
            gym.register(
                id=env_id, entry_point=entry_point, kwargs=dict(kwargs), disable_env_checker=False
            )


def family(cfg_or_name: Config | str) -> Family:
    """The registry entry of a config (its ``family``) or of a family name."""
    name = cfg_or_name if isinstance(cfg_or_name, str) else cfg_or_name.family
    if name not in FAMILIES:
        broken = FAMILIES.broken.get(name)
        if broken:
            raise ValueError(f"family {name!r} is installed but could not be loaded: {broken}")
        raise ValueError(f"family must be one of {sorted(FAMILIES)}, got {name!r}")
    return FAMILIES[name]


__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "Experiment",
    "FAMILIES",
    "HELDOUT_SEED",
    "HELDOUT_SEEDS",
    "HELDOUT_SIZE",
    "Family",
    "PatchLayout",
    "TestDistribution",
    "family",
    "one_of",
    "register_family",
    "sealed_episode_seed",
    "register_gym_ids",
]
