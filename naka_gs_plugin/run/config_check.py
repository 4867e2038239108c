"""A run's configuration checked before it is used: one line naming the key, the value and the fix.

nerfstudio reads a run's ``config.yml`` (``ns-train --load-config``, ``ns-eval``, ``ns-render``, ``ns-export``,
``ns-viewer``) with ``yaml.Loader``, which sets whatever keys the file holds as attributes: a misspelt key
(``sh_degre: 1``) is ignored in silence, the run using the default, and a value of the wrong type
(``sh_degree: three``) fails later as a ``TypeError`` deep in the model. Our docs tell users to edit config.yml,
so :func:`check_run_config` refuses both, naming the nearest known key, and also values out of range, from the
file or from ns-train's options (``--max-num-iterations 0``, ``--pipeline.model.sh-degree -1``).

A config.yml that is not YAML, empty, or not a run's configuration fails inside upstream's loader before any of
our code runs. ns-train's ``--load-config`` file is checked before it is read
(:meth:`~naka_gs_plugin.trainer.NakaGSTrainerConfig.__post_init__`, :func:`check_config_file`); the commands that
load a run read it in ``eval_setup``, whose errors :mod:`naka_gs_plugin.run.nerfstudio_hooks` turns into these lines.

A config.yml is data: people share run folders, and ``yaml.Loader`` runs whatever a ``!!python/object/apply`` tag
names while it reads the file. :func:`refuse_code_in_config` reads the file's node tree first (composing runs
nothing) and lets through only the tags a run's config holds (:func:`allowed_tag`); anything else is one line naming
the tag, the file and its line, before nerfstudio or we construct anything from it.

The presets register themselves (:func:`register_presets`) so that a message can name an option's default without
this module importing them: they are the roof of the package, this module a floor below.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import functools
import importlib
import os
import stat
import types
import typing
from pathlib import Path, PurePath
from typing import Any, Dict, Iterator, Literal, Mapping, Optional, Tuple, Union

import yaml

RANGES: Dict[str, Tuple[int, Optional[int], str, str]] = {
    "max_num_iterations": (1, None, "the number of training steps", ""),
    "pipeline.model.sh_degree": (0, 4, "the spherical-harmonics degree", " (above 3 only with gsplat on CUDA)"),
}
"""Whole-number options checked for their range: dotted key -> (least, most or None, what it is, a note)."""


def _flag(dotted: str) -> str:
    return "--" + dotted.replace("_", "-")


@functools.lru_cache(maxsize=None)
def _hints(cls: type) -> Dict[str, Any]:
    """The field types of a dataclass, or {} where they cannot be resolved (only its keys are checked then)."""
    try:
        return typing.get_type_hints(cls)
    except Exception:
        return {}


def _mismatch(value: Any, hint: Any) -> Optional[str]:
    """What ``hint`` asks for, when ``value`` is clearly not that; None when it fits or cannot be told."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        wanted = [_mismatch(value, arg) for arg in args]
        return None if None in wanted else " or ".join(wanted)  # type: ignore[arg-type]
    if origin is Literal:
        return (
            None
            if any(value == arg and type(value) is type(arg) for arg in args)
            else ("one of " + ", ".join(str(arg) for arg in args))
        )
    if hint is type(None):
        return None if value is None else "null"
    if hint is bool:
        return None if isinstance(value, bool) else "true or false"
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "a whole number"
    if hint is float:
        return None if isinstance(value, (int, float)) and not isinstance(value, bool) else "a number"
    if hint is str:
        return None if isinstance(value, str) else "a string"
    if isinstance(hint, type) and issubclass(hint, PurePath):
        return None if isinstance(value, PurePath) else "a path"
    if origin in (tuple, list) or hint in (tuple, list):
        return None if isinstance(value, (tuple, list)) else "a list"
    if origin is dict or hint is dict:
        return None if isinstance(value, dict) else "a mapping (key: value lines)"
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return None if dataclasses.is_dataclass(value) and not isinstance(value, type) else f"a {hint.__name__} block"
    return None  # Type[...], Callable, Any...: not checked


def _is_path_hint(hint: Any) -> bool:
    options = typing.get_args(hint) if typing.get_origin(hint) in (Union, types.UnionType) else (hint,)
    return any(isinstance(option, type) and issubclass(option, PurePath) for option in options)


PRESETS: Dict[str, Any] = {}
"""The registered presets' configs by method name (filled by :func:`register_presets`)."""


def register_presets(configs: Mapping[str, Any]) -> None:
    """Record the presets' configs (``method_name`` -> config), whose values the messages name as defaults."""
    PRESETS.update(configs)


def _default(config: Any, dotted: str) -> Any:
    """The value of ``dotted`` in the registered preset the run was made with, if there is one."""
    value: Any = PRESETS.get(getattr(config, "method_name", None))
    for part in dotted.split("."):
        value = value.get(part) if isinstance(value, dict) else getattr(value, part, None)
    return value


def _problems(obj: Any, where: str, names: Dict[str, str]) -> Iterator[Tuple[str, str, Any, str]]:
    """``(kind, dotted key, value, detail)`` for each unknown key or wrong-typed value under ``obj``: kind
    ``unknown`` (detail: the nearest known key's hint) or ``type`` (detail: what the field takes). A string where
    a path is expected is taken as that path (a hand-edited ``data: /my/scene``)."""
    prefix = f"{where}." if where else ""
    if isinstance(obj, dict):
        for key, value in obj.items():
            yield from _problems(value, f"{prefix}{key}", names)
        return
    if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        return
    fields = {f.name for f in dataclasses.fields(obj)}
    hints = _hints(type(obj))
    for key, value in list(vars(obj).items()):
        if key.startswith("_") and key not in fields:
            continue  # set by our own code (the run folder a config was loaded from), never written to config.yml
        dotted = f"{prefix}{key}"
        if key not in fields:
            near = difflib.get_close_matches(key, sorted(fields), n=1, cutoff=0.6)
            elsewhere = names.get(key)
            hint = (
                f" (did you mean {prefix}{near[0]}?)"
                if near
                else (f" (it belongs under {elsewhere})" if elsewhere else "")
            )
            yield "unknown", dotted, value, hint
            continue
        hint = hints.get(key)
        if hint is not None:
            if isinstance(value, str) and _is_path_hint(hint):
                value = Path(value)
                setattr(obj, key, value)
            wanted = _mismatch(value, hint)
            if wanted is not None:
                yield "type", dotted, value, wanted
                continue
        yield from _problems(value, dotted, names)


def _field_owners(obj: Any, where: str = "", found: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """Every field name in the tree under ``obj`` -> the dotted block that has it (the first one met)."""
    found = {} if found is None else found
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for field in dataclasses.fields(obj):
            found.setdefault(field.name, where or "the top level")
            if field.name in vars(obj):
                _field_owners(vars(obj)[field.name], f"{where}.{field.name}" if where else field.name, found)
    elif isinstance(obj, dict):
        for key, value in obj.items():
            _field_owners(value, f"{where}.{key}" if where else str(key), found)
    return found


def _value(config: Any, dotted: str) -> Any:
    value = config
    for part in dotted.split("."):
        value = getattr(value, part, None)
    return value


def run_config_problem(config: Any, source: Optional[Path]) -> Optional[str]:
    """The one line (``naka-gs: ...``) for the first problem of ``config``, else None: an unknown key or a value
    of the wrong type (only a loaded config.yml can have those) or a value out of :data:`RANGES`. ``source`` is
    the config.yml it was loaded from (its keys are named as in the file), None for ns-train's options."""
    for kind, dotted, value, detail in _problems(config, "", _field_owners(config)):
        where = source if source is not None else "the loaded configuration"
        if kind == "unknown":
            return (
                f"naka-gs: {where}: unknown key {dotted}{detail} -- correct or delete it in that file "
                "(nerfstudio would ignore it and use the default)"
            )
        default = _default(config, dotted)
        example = f" (the default is {default})" if default is not None else ""
        return f"naka-gs: {where}: {dotted} is {value!r}, not {detail} -- write {detail} there{example}"
    for dotted, (least, most, what, note) in RANGES.items():
        value = _value(config, dotted)
        if not isinstance(value, int) or (value >= least and (most is None or value <= most)):
            continue
        rule = ("nothing to train; " if dotted == "max_num_iterations" and value == 0 else "") + (
            f"{what} must be " + (f"at least {least}" if most is None else f"{least} to {most}") + note
        )
        default = _default(config, dotted)
        if source is not None:
            example = f" (the default is {default})" if default is not None else ""
            return (
                f"naka-gs: {source}: {dotted}: {value} is out of range; {rule} -- write a value in that range "
                f"there{example}"
            )
        example = f", e.g. {_flag(dotted)} {default} (the default)" if default is not None else ""
        return f"naka-gs: {_flag(dotted)} {value}: {rule} -- pass a value in that range{example}"
    return None


def check_run_config(config: Any, source: Optional[Path]) -> None:
    """Exit with :func:`run_config_problem`'s line (status 1) when there is one."""
    line = run_config_problem(config, source)
    if line is not None:
        raise SystemExit(line)


def config_file_problem(path: Path, text: str, loaded: Any) -> Optional[str]:
    """The one line for a config.yml that loaded as ``loaded`` but is not a run's configuration, else None."""
    from nerfstudio.engine.trainer import TrainerConfig

    if isinstance(loaded, TrainerConfig):
        return None
    if loaded is None and not text.strip():
        return (
            f"naka-gs: {path}: the file is empty -- it should hold the configuration ns-train wrote for the run: "
            "restore it from a copy, or train the run again"
        )
    return (
        f"naka-gs: {path}: holds {type(loaded).__name__ if loaded is not None else 'null'}, not a nerfstudio run "
        "configuration -- pass the config.yml ns-train wrote in a run folder (<output-dir>/<scene>/<method>/<timestamp>)"
    )


def yaml_error_line(path: Path, err: yaml.YAMLError) -> str:
    """The one line for a config.yml that YAML cannot read: the problem and where, with the fix."""
    mark = getattr(err, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    problem = getattr(err, "problem", None) or " ".join(str(err).split())
    return (
        f"naka-gs: {path}: not a readable YAML file ({problem}{where}) -- fix that line, or restore the config.yml "
        "ns-train wrote"
    )


def unreadable_line(path: Path, err: Exception) -> str:
    why = "not a text file" if isinstance(err, UnicodeDecodeError) else (getattr(err, "strerror", None) or str(err))
    return f"naka-gs: {path}: cannot read it ({why}) -- pass the config.yml ns-train wrote in a run folder"


STANDARD_TAGS = frozenset(
    f"tag:yaml.org,2002:{name}"
    for name in ("str", "int", "float", "bool", "null", "map", "seq", "timestamp", "python/tuple")
)
"""YAML's standard scalars and collections, and the tuples nerfstudio's configs hold."""
TRUSTED_MODULES = ("nerfstudio.", "naka_gs_plugin.", "torch.optim.")
"""The packages whose classes a run's config.yml may name (configs, their ``_target`` classes, optimizers)."""
PATH_CLASSES = ("pathlib.Path", "pathlib.PosixPath", "pathlib.WindowsPath", "pathlib.PurePosixPath")
PYTHON_TAG = "tag:yaml.org,2002:python/"


def _trusted_class(dotted: str) -> Optional[type]:
    """The class ``dotted`` names when it lives in one of :data:`TRUSTED_MODULES`, else None (nothing outside them
    is imported)."""
    module, _, name = dotted.rpartition(".")
    if not module or not (module + ".").startswith(TRUSTED_MODULES):
        return None
    try:
        found = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return None
    return found if isinstance(found, type) else None


def allowed_tag(tag: str) -> bool:
    """Whether a config.yml may hold ``tag``: a standard one; a path (``!!python/object/apply:pathlib.PosixPath``);
    a dataclass of nerfstudio or ours (``!!python/object:``, built without calling it); an enum of those
    (``!!python/object/apply:``, nerfstudio's writer events); a class of those, or a torch optimizer
    (``!!python/name:``, the ``_target`` of a config)."""
    if tag in STANDARD_TAGS:
        return True
    if not tag.startswith(PYTHON_TAG):
        return False
    kind, _, dotted = tag[len(PYTHON_TAG) :].partition(":")
    if kind == "object/apply" and dotted in PATH_CLASSES:
        return True
    cls = _trusted_class(dotted) if kind in ("object", "object/apply", "name") else None
    if cls is None:
        return False
    if kind == "object":
        return dataclasses.is_dataclass(cls)
    if kind == "object/apply":
        return issubclass(cls, enum.Enum)
    return True


def _nodes(node: yaml.Node) -> Iterator[yaml.Node]:
    stack, seen = [node], set()
    while stack:
        node = stack.pop()
        if id(node) in seen:  # an alias shares its node
            continue
        seen.add(id(node))
        yield node
        if isinstance(node, yaml.MappingNode):
            stack.extend(part for pair in node.value for part in pair)
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)


class RunConfigLoader(yaml.Loader):
    """nerfstudio's loader for a run's config.yml, constructing only the tags :func:`allowed_tag` lets through: a
    file :func:`refuse_code_in_config` has not seen still builds nothing else."""

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        if not allowed_tag(node.tag):
            raise yaml.constructor.ConstructorError(
                None, None, f"the tag {node.tag} is not one a run's config.yml holds", node.start_mark
            )
        return super().construct_object(node, deep)


def refuse_code_in_config(path: Path, text: str) -> None:
    """Exit with one line (status 1) when ``text``, the config.yml at ``path``, holds a tag a run's config does not
    (:func:`allowed_tag`), naming the tag and its line; nothing in the file is constructed or run. YAML it cannot
    read is left to the caller's error line."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return
    for node in _nodes(root) if root is not None else ():
        if not allowed_tag(node.tag):
            tag = (
                "!!" + node.tag[len("tag:yaml.org,2002:") :] if node.tag.startswith("tag:yaml.org,2002:") else node.tag
            )
            raise SystemExit(
                f"naka-gs: {path}: line {node.start_mark.line + 1} holds the tag {tag}, which a run's config.yml "
                "never holds (it would run code while the file is read); nothing was run -- delete that entry, or "
                "restore the config.yml ns-train wrote"
            )


def read_regular_text(path: Path, limit: int = 64 << 20) -> str:
    """The text of ``path`` when it is a regular file (a FIFO or device would block or never end), at most ``limit``
    bytes; raises OSError / UnicodeDecodeError as ``read_text`` does."""
    with open(path, "rb", opener=lambda p, flags: os.open(p, flags | os.O_NONBLOCK)) as fh:
        if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
            raise OSError(0, "not a regular file", str(path))
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise OSError(0, f"over {limit >> 20} MB, not a run's config.yml", str(path))
    return data.decode()


def check_config_file(path: Path) -> None:
    """Exit with one line (status 1) when ``path`` cannot be read, holds code (:func:`refuse_code_in_config`), is not
    YAML, not a run's configuration, or holds a problem of :func:`run_config_problem`; ``ns-train --load-config`` is
    checked so before it reads the file."""
    try:
        text = read_regular_text(Path(path))
    except (OSError, UnicodeDecodeError) as err:
        raise SystemExit(unreadable_line(path, err)) from None
    refuse_code_in_config(path, text)
    try:
        loaded = yaml.load(text, Loader=RunConfigLoader)
    except yaml.YAMLError as err:
        raise SystemExit(yaml_error_line(path, err)) from None
    line = config_file_problem(path, text, loaded) or run_config_problem(loaded, path)
    if line is not None:
        raise SystemExit(line)
