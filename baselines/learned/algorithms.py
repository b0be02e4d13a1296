"""The learning algorithms, one entry each: the one list that the CLI's ``--algo``, the saved policy's loader, the
BenchMARL configurations and the studies read.

An :class:`Algorithm` names the libraries that train it (``sb3``, ``rllib``: ``train.py``; ``benchmarl``), whether
it learns on-policy, the library's class (SB3's ``PPO``, BenchMARL's ``MappoConfig``) and its hyperparameter file,
YAML in this package: ``algorithm_conf/<name>.yaml`` for SB3, BenchMARL's own layout for BenchMARL
(:mod:`~ee_formation_env.baselines.learned.benchmarl_configs`). A new algorithm, or a variant of one with other
hyperparameters, is one YAML file and one line in :data:`BUILTIN_ALGORITHMS` (docs/extending.md).
:func:`read_hyperparameters` reads an SB3 file, checked against the keys and types its caller accepts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import yaml

#: The folder the hyperparameter files are named relative to (the installed package's).
PACKAGE_DIR = Path(__file__).parent


@dataclass(frozen=True)
class Algorithm:
    """One learning algorithm (module docstring)."""

    name: str
    backends: tuple[str, ...]  # the libraries that train it: sb3 and rllib (train.py), benchmarl
    on_policy: bool  # learns from fresh rollouts of its current policy (PPO's family), not from a replay buffer
    library_class: str  # the library's class: SB3's algorithm, BenchMARL's algorithm config
    hyperparameters: str  # its YAML file, relative to PACKAGE_DIR (or absolute)

    @property
    def is_ppo(self) -> bool:
        """Whether SB3's (or RLlib's) PPO trains it: the mode presets' PPO settings, gSDE, set networks,
        ``--imitate`` and ``--resume`` apply."""
        return self.library_class == "PPO"

    @property
    def hyperparameter_path(self) -> Path:
        return PACKAGE_DIR / self.hyperparameters


#: The built-in algorithms, in the order the CLI lists them (the default first).
BUILTIN_ALGORITHMS = (
    Algorithm("ppo", ("sb3", "rllib"), True, "PPO", "algorithm_conf/ppo.yaml"),
    Algorithm("sac", ("sb3",), False, "SAC", "algorithm_conf/sac.yaml"),
    Algorithm("mappo", ("benchmarl",), True, "MappoConfig", "benchmarl_conf/algorithm/mappo.yaml"),
    Algorithm("ippo", ("benchmarl",), True, "IppoConfig", "benchmarl_conf/algorithm/ippo.yaml"),
    Algorithm("masac", ("benchmarl",), False, "MasacConfig", "benchmarl_conf/algorithm/masac.yaml"),
)
_ALGORITHMS: dict[str, Algorithm] = {entry.name: entry for entry in BUILTIN_ALGORITHMS}


def register_algorithm(entry: Algorithm) -> Algorithm:
    """Add ``entry`` (a variant for a test, say); ``ValueError`` if its name is taken."""
    if not isinstance(entry, Algorithm) or not entry.name:
        raise TypeError(f"algorithm: expected an Algorithm with a name, got {entry!r}")
    if entry.name in _ALGORITHMS:
        raise ValueError(f"algorithm: {entry.name!r} is already registered")
    _ALGORITHMS[entry.name] = entry
    return entry


def unregister_algorithm(name: str) -> None:
    """Remove the algorithm ``name`` (one registered for a test)."""
    _ALGORITHMS.pop(name, None)


def algorithm_names(*backends: str) -> tuple[str, ...]:
    """The registered algorithms' names, in registration order; with ``backends``, those one of them trains."""
    return tuple(name for name, entry in _ALGORITHMS.items()
                 if not backends or any(backend in entry.backends for backend in backends))


def algorithm(name: Any, field: str = "algo", backends: Sequence[str] = ()) -> Algorithm:
    """The registered algorithm ``name`` (one that ``backends`` train, where given); ``ValueError`` naming
    ``field``."""
    names = algorithm_names(*backends)
    if not isinstance(name, str) or name not in names:
        raise ValueError(f"{field}: expected one of {list(names)}, got {name!r}")
    return _ALGORITHMS[name]


class AlgorithmNames(Sequence[str]):
    """The names of the algorithms ``backends`` train, read from the registry when used: an argparse ``choices``
    that sees an algorithm registered after the parser was made."""

    def __init__(self, *backends: str):
        self.backends = backends

    def _names(self) -> tuple[str, ...]:
        return algorithm_names(*self.backends)

    def __getitem__(self, index: Any) -> Any:
        return self._names()[index]

    def __len__(self) -> int:
        return len(self._names())

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())

    def __contains__(self, name: object) -> bool:
        return name in self._names()

    def __repr__(self) -> str:
        return repr(self._names())


def _fits(value: Any, example: Any) -> bool:
    """Whether ``value`` has the type of ``example`` (the library's default): a bool for a bool, an integer for an
    integer, a number for a float; a string default (``"auto"``) also takes a number, a ``None`` one any scalar."""
    if isinstance(example, bool):
        return isinstance(value, bool)
    if isinstance(value, bool):
        return example is None
    if isinstance(example, int):
        return isinstance(value, int)
    if isinstance(example, float):
        return isinstance(value, (int, float))
    if isinstance(example, str):
        return isinstance(value, (str, int, float))
    return example is None and isinstance(value, (str, int, float))


def read_hyperparameters(entry: Algorithm, accepted: Mapping[str, Any]) -> dict[str, Any]:
    """The hyperparameters in ``entry``'s YAML file: a mapping whose keys are in ``accepted`` (key -> an example
    value, the library's default, whose type the value must have). A fault is a ``ValueError`` naming the file
    and the key."""
    path = entry.hyperparameter_path
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"{path}: unreadable hyperparameters ({str(error).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of hyperparameters, got {type(data).__name__}")
    for key, value in data.items():
        if key not in accepted:
            raise ValueError(f"{path}: {key}: unknown key for {entry.library_class} (accepted: "
                             f"{', '.join(sorted(map(str, accepted)))})")
        if not _fits(value, accepted[key]):
            raise ValueError(f"{path}: {key}: expected a value of the type of {accepted[key]!r}, got {value!r}")
    return data
