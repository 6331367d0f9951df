"""The family contract and registry: what each task family brings, behind one public contract
(docs/families.md).

A family is a distribution over MDPs sharing states and actions (paper §2): its batched env, its
options (subtasks), its named instance and test distributions, and what the heads, the exact oracle
and the experiments can use of it. Everything that depends on the family reads the registry
(:func:`family`) instead of testing the family's name, so a new family needs no edit of the package:

- :func:`register_family` adds one from code in the same process;
- the entry-point group ``taskvar_torch.families`` adds those of any installed package (the way
  Gymnasium and pytest find plugins), so the installed ``taskvar`` command sees them; an entry
  point names a :class:`Family` or a callable returning one;
- :func:`check_family` checks the contract and names what is missing in one line.

The built-in families (``taskvar_torch/families/<name>/``) come through the same door as an
installed package's: :data:`BUILTIN` names their entry points. This module sits at the bottom of
the package (it imports only :mod:`taskvar_torch.rng`), so every layer may read the registry.

Examples:
    >>> family("windy").experiment.name
    'windy-fig2'
    >>> sorted(FAMILIES)[:2]
    ['taxi', 'wargus']
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
    """The env seed under which the bundle of training seed ``training_seed`` plays the sealed
    test seed ``sealed`` (docs/evaluation.md, Seed): ``rng.sub_env_key(sealed, training_seed)``,
    a 32-bit hash. Each training seed thus plays its own independent draw of the sealed test
    distribution (its instances' distribution unchanged, other episodes), so a CI over training
    seeds counts the episodes' noise too; every method of one bundle plays the same draw (paired).
    Distinct training seeds always get distinct seeds (the hash is a bijection of the key)."""
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
    """A named test distribution of a family (``taskvar eval --test NAME``): which instances its
    episodes draw and which env keys it changes from the bundle's training config.

    Attributes:
        description: what it shifts, in one line (docs/evaluation.md lists them all).
        instances: a named instance distribution or the fields of one (a dict).
        overrides: config overrides of ``env`` keys (``key=value``), validated like a config.
        seed: a sealed test seed (``HELDOUT_SEED``): ``taskvar eval`` plays it, drawn for the
            bundle's training seed (:func:`sealed_episode_seed`), and refuses another ``--seed``;
            ``None``: the evaluation's seed (the bundle's ``seed + 1``).
    """

    __test__ = False  # not a pytest test class

    description: str
    instances: Any = "train"
    overrides: tuple[str, ...] = ()
    seed: int | None = None


@dataclass(frozen=True)
class Experiment:
    """One experiment: its module and the names of its entry points there (``taskvar experiment
    NAME``). A family declares its figure experiment (``Family.experiment``); the registry
    (:mod:`taskvar_torch.experiments.registry`) lists every family's and the scale experiment.

    Attributes:
        name: ``taskvar experiment NAME`` and ``metrics.json``'s ``"experiment"``.
        module: dotted module holding the functions below.
        run: the function running it (``run(cfg, out_dir, ...) -> metrics``).
        plot: ``plot(out_dir) -> [png paths]`` (redraws from the results folder alone).
        default_config: ``default_config() -> Path`` of its YAML config.
        schema: the config dataclass its YAML follows (``Config`` or ``ScaleConfig``).
        loader: ``loader(path, overrides, quick=...) -> config`` in its module, for a schema
            other than ``Config`` (``Config``: :func:`taskvar_torch.config.load_config`).
        description: one line for ``--help``.
        config_class: the experiment's own keys, a frozen dataclass read flat under
            ``experiment.*`` beside the keys every config has (``runs``, ``quick_overrides``), in a
            config of the family that declares it only (another family's config refuses them as
            unknown keys); ``None``: no own keys. Checked by the family's ``validate``.
        refusals: why the experiment does not take an option of ``taskvar experiment`` (option
            -> the one-line reason); an option it neither takes nor names here is refused with
            a generic line.
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

    The first five attributes are required; the rest are optional capabilities (``None``: the
    family does not offer it, and the commands that need it say so in one line). docs/families.md
    has the contract the env and the subtasks must honour, and a walk-through.

    Attributes:
        name: the config's ``family`` value.
        env_class: the batched TorchRL env (a ``BatchedFamilyEnv``); its constructor takes
            ``num_envs``, ``seed``, ``instances``, ``index_offset``, ``noise_seed`` and
            ``validate_actions`` besides what ``env_kwargs`` gives.
        env_kwargs: config -> keyword arguments of ``env_class`` for the training env.
        subtasks: (config, env) -> the family's options (a :class:`Subtasks`).
        instance_names: the named instance distributions (``env.instances``, ``eval.test``).
        config_class: the family's own env keys, a frozen dataclass read under
            ``env.<name>`` (strictly: a misspelt key is a one-line error naming it; its
            ``__post_init__`` range errors start with the field's name). ``None``: no own keys.
        validate: extra checks of a config of this family; raises a one-line ``ValueError``.
        tests: the named test distributions (``taskvar eval --test``), the first the default.
        instance_fields: an instance distribution (name, dict or object) -> its fields as a dict,
            for ``--shift env.instances.FIELD=...``; ``None``: the instances cannot be shifted.
        make_instances: fields -> an instance distribution (raises a one-line ``ValueError``).
        shift_aliases: extra ``env.instances.FIELD`` names ``make_instances`` accepts (windy's
            ``p``: one wind strength for the band).
        instance_dim: features of the hidden instance the heads may read offline
            (``train.max_value_estimator=instance``), computed by ``instance_features``.
        instance_features: a tensordict of transitions -> ``(B, instance_dim)`` features of
            their ``("instance", ...)`` entries.
        informed_features: config -> ``(dim, features)``, what the ``informed`` baseline reads
            beside the observation (docs/memory.md): ``features`` maps transitions to ``(B, dim)``
            features of the hidden instance and state. ``None``: ``(instance_dim,
            instance_features)``. Its own hook because its dimension may depend on the config
            (Wargus: the item and patrol positions) and because only the baseline reads it, never
            the ``instance`` max-value estimator (Definition 1's max over instances).
        oracle: config -> the family's exact oracle for that env, or ``None`` where it has none
            (too large, another encoding): an
            :class:`~taskvar_torch.oracle.protocol.ExactOracle` (docs/families.md; not imported
            here: this module is the package's bottom).
        oracle_summary: (heads, config) -> lines comparing the learnt heads with the exact oracle
            (printed after ``taskvar train``); ``None``: nothing printed.
        averaging_optimum: config -> the exact mean-MDP averaging policy ``(cells,)`` over
            ``cell``, the scale experiment's reference (also for grids too large for ``oracle``).
        head_report: (config, heads, with_max_value) -> every head against exact values (the
            scale experiment's ``head_report``).
        experiment: the family's figure experiment (an :class:`Experiment`: ``taskvar experiment
            NAME``, sweeps); the experiment registry lists every family's.
        grid_side: config -> the grid's side length (the scale experiment's tables).
        cells: config -> the number of positions of the agent.
        observation: config -> the observation encoding's name.
        observation_size: config -> the observation's length, without building the env (the
            memory estimate, :mod:`taskvar_torch.config.memory`); ``None``: read from a
            one-environment env.
        conv_patch: config -> the observation's patch layout (``heads.network=conv``).
        option_inputs: the subtasks define per-option input features
            (``heads.option_inputs=subtask``).
        description: one line for listings.
        gym_ids: the Gymnasium ids the family registers (``gym.make(id)``): id -> ``(entry
            point "module:Class", keyword arguments)``, registered when the family is (lazily:
            nothing is imported until ``gym.make``); :func:`taskvar_torch.envs.registration
            .register_envs` registers every family's on ``import taskvar_torch``.
        legacy_env_keys: keys of ``config_class`` that configs of an older version held
            elsewhere: ``KEY`` at ``env.KEY``, or the dotted path it had (``train.composed_reward``);
            the loader moves them to ``env.<name>.*`` with a deprecation line (and an override
            ``env.KEY=V`` likewise: :func:`taskvar_torch.config.migration.migrate_overrides`).
        legacy_section: configs of an older version held ``env.<name>`` whatever their family;
            the loader drops it from another family's config with a deprecation line.
        resumable: a checkpoint's ``env.state_dict()`` continues every episode exactly
            (``runtime_state``); ``False`` (an env whose state lives outside tensors, e.g. the
            Gymnasium adapter's): ``taskvar train --resume`` refuses in one line and
            ``check_family`` skips the resume check.
        failed_below: what failure means for the family's score (docs/report.md#failed-seeds):
            a training seed whose score in a ``taskvar report`` row (its mean return per episode,
            the number the compact tables show) is below this failed: it does not reach the goal
            the reward pays for; the row's cell says ``k/n seeds failed``. Chosen from the
            family's reward definition alone, never from results. ``None``: no failure rule.
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
        """The family's batched env of ``cfg`` (no transforms). ``None`` keeps the config's value
        (``env.num_envs``, ``seed``, ``env.instances``); ``index_offset`` is the global index of
        sub-environment 0 in the keyed streams (envs with offsets 0, n, 2n... are disjoint slices
        of one env of the summed size); ``noise_seed`` keys the per-step noise apart from the
        instances (common random numbers for paired episodes)."""
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
    """The built-in families (:data:`BUILTIN`) and the ``taskvar_torch.families`` entry points of
    every installed distribution, as entry points loaded the same way.

    The built-ins come first and from :data:`BUILTIN` itself, so a source checkout whose installed
    metadata is stale still has them. Every copy of a distribution's metadata is read, not only
    the first on ``sys.path`` (which ``importlib.metadata.entry_points`` keeps): a stale
    ``*.egg-info`` left in a source checkout would otherwise hide the installed package's entry
    points when run from that folder.
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
    """Every family by name: the ones registered in this process and those of installed packages'
    ``taskvar_torch.families`` entry points.

    An entry point is imported only when its family is asked for by name (``FAMILIES[name]``,
    ``name in FAMILIES``, :func:`family`): a plugin that hangs, crashes or exits on import cannot
    take down a command that does not use it. Iterating gives every name (the entry points' read
    from the installed metadata, nothing imported); :meth:`values` and :meth:`items` import every
    family, :meth:`loaded` only those already imported and the built-in ones. A plugin that fails
    to load is one warning naming it, and its name is in :attr:`broken`.
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
    """Add ``fam`` to the registry, so every command, experiment and controller can use it.

    Args:
        fam: the family (see :class:`Family` and docs/families.md for the contract).
        replace: replace a family of the same name registered earlier (never a built-in one).

    Returns:
        ``fam``.

    Raises:
        ValueError: in one line, a declaration that breaks the contract, a name of a built-in
            family, or a name already taken (without ``replace``).

    Examples:
        >>> register_family(Family(name="corridor", env_class=CorridorEnv, ...))  # doctest: +SKIP
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
