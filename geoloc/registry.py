"""One way to plug in a component: a registry per kind, keyed by the `name` field of its config section.

    @register("loss", "my_loss")
    def my_loss(margin: float = 0.3) -> nn.Module: ...

    # my_conf/loss/my_loss.yaml (my_conf: any folder on hydra.searchpath)
    name: my_loss
    module: my_project.losses      # imported before the lookup: a module name or a path to a .py file
    margin: 0.3

`build(kind, section, **runtime)` imports `module` when given, looks `name` up, checks the remaining keys against
the factory's signature and calls it with them plus the runtime arguments the caller supplies (a head gets its
backbone's channels, a loss its descriptor dimension...). An unknown name or argument fails at start-up, naming the
key and the choices. docs/extending.md lists the kinds and what each factory receives and returns.

Who declares a kind, and how its built-ins are found: the package that owns a kind declares it with
`declare(kind, section)` and registers its built-ins in the same package, so importing the owner is all it takes
for a lookup to see them; code that builds a kind imports its owner (it uses it anyway). The component layers own
theirs (geoloc.datasets: dataset, geoloc.models.backbones: backbone, ...), a task owns the kinds only it builds
(geoloc.tasks.mmdip: segmenter, generator_loss, mmdip_dataset), and geoloc.tasks owns the task kind, whose
built-ins it finds rather than imports: its `load` imports every package under geoloc/tasks/ on the first lookup.
So this module imports nothing above geoloc.config and names no package: no list here has to grow with geoloc.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from omegaconf import DictConfig, OmegaConf

from geoloc.config import ConfigError

RESERVED = ("name", "module")


@dataclass(frozen=True)
class Kind:
    """A kind of component: the config section its components are read from and the key that names one."""

    name: str
    section: str
    name_key: str
    runtime: tuple[str, ...] = ()  # the arguments geoloc passes a factory at run time: not config keys
    load: Callable[[], None] | None = None  # finds the built-ins that importing the owner does not register


_kinds: dict[str, Kind] = {}
# kind -> name -> factory; a plug-in may register before the kind's owner is imported and declares it
_registry: dict[str, dict[str, Any]] = {}
_loaded: set[str] = set()


def declare(kind: str, section: str, *, name_key: str | None = None, runtime: tuple[str, ...] = (),
            load: Callable[[], None] | None = None) -> None:
    """Called by the package that owns `kind`: its components come from config `section`, named by `name_key`
    (default `<section>.name`), and are passed the `runtime` arguments by the code that builds them
    (docs/extending.md). Declaring again the same way is a no-op; declaring it differently is an error."""
    declared = Kind(kind, section, name_key or f"{section}.name", tuple(runtime), load)
    known = _kinds.get(kind)
    if known is not None and (known.section, known.name_key, known.runtime) != (
            declared.section, declared.name_key, declared.runtime):
        raise ValueError(f"component kind {kind!r} is already declared for config section '{known.section}'")
    if known is None:
        _kinds[kind] = declared
    _registry.setdefault(kind, {})


def register(kind: str, name: str, obj: Any = None) -> Any:
    """Decorator: make `fn` buildable as `<section>.name=<name>`; `register(kind, name, obj)` registers `obj`
    directly (a task package registers its module). Registering a taken name is an error."""

    def add(fn: Any) -> Any:
        entries = _registry.setdefault(kind, {})
        taken = entries.get(name)
        if taken is not None and taken is not fn and _origin(taken) != _origin(fn):
            raise ValueError(f"{kind} {name!r} is already registered by {_qualname(taken)}; pick another name")
        entries[name] = fn
        return fn

    return add if obj is None else add(obj)


def kinds() -> dict[str, Kind]:
    """The kinds declared so far (by the packages imported so far)."""
    return dict(_kinds)


def section(kind: str) -> str:
    """The config section a kind's components are read from."""
    return _declared(kind).section


def runtime(kind: str) -> tuple[str, ...]:
    """The arguments geoloc passes a kind's factories at run time (they are not config keys)."""
    return _declared(kind).runtime


def names(kind: str) -> list[str]:
    _declared(kind)
    return sorted(_registry[kind])


def lookup(kind: str, name: str) -> Any:
    declared = _declared(kind)
    if name not in _registry[kind]:
        raise ConfigError(f"{declared.name_key}={name!r} is not a known {kind}; choose one of {names(kind)}, or add "
                          f"one from your own module (docs/extending.md){_stray_hint()}")
    return _registry[kind][name]


def find(kind: str, section: DictConfig | dict, where: str | None = None) -> Any:
    """The registered object `section.name` names, after importing `section.module` when given."""
    params = _as_dict(section)
    where = where or _declared(kind).section
    if "name" not in params:
        raise ConfigError(f"config section '{where}' has no 'name'; choose one of {names(kind)}")
    import_module(params.get("module"), where)
    return lookup(kind, params["name"])


def build(kind: str, section: DictConfig | dict, *, exclude: tuple[str, ...] = (), where: str | None = None,
          **runtime: Any) -> Any:
    """Build the `kind` named by `section.name` with the section's other keys (minus `exclude`) plus `runtime`.
    `where` is the config path the section's keys are reported under (default: the kind's section)."""
    factory, params, runtime = _resolve(kind, section, exclude, runtime, where)
    return factory(**params, **runtime)


def check(kind: str, section: DictConfig | dict, *, exclude: tuple[str, ...] = (), where: str | None = None) -> None:
    """build()'s checks without building, the kind's run-time arguments taken as given: for what is built later
    (an optimizer needs the network first)."""
    _resolve(kind, section, exclude, dict.fromkeys(_declared(kind).runtime), where)


def with_defaults(kind: str, section: DictConfig | dict) -> dict:
    """`section` with every config key of its factory present: the factory's signature defaults (run-time
    arguments excepted; tuples as lists), overlaid with the section's own values."""
    params = _as_dict(section)
    factory = find(kind, params)
    keys = {}
    for key, param in inspect.signature(factory).parameters.items():
        if key in _declared(kind).runtime or param.kind not in (param.POSITIONAL_OR_KEYWORD, param.KEYWORD_ONLY):
            continue
        default = None if param.default is param.empty else param.default
        keys[key] = list(default) if isinstance(default, tuple) else default
    named = {k: params[k] for k in RESERVED if k in params}
    return {**named, **keys, **params}


def _resolve(kind: str, section, exclude: tuple[str, ...], runtime: dict,
             where: str | None) -> tuple[Callable, dict, dict]:
    """(factory, its config keys, the runtime arguments it takes), checked: the plug-in module imported, the name
    known, every key an argument and every argument without a default given."""
    where = where or _declared(kind).section
    factory = find(kind, section, where)
    params = {k: v for k, v in _as_dict(section).items() if k not in RESERVED and k not in exclude}
    runtime = accepted(factory, runtime)
    check_arguments(factory, params, runtime, _qualname(factory), where)
    return factory, params, runtime


def accepted(factory: Callable, runtime: dict) -> dict:
    """The runtime arguments the factory takes: a plug-in asks only for what it needs (a loss may ignore `dim`)."""
    parameters = inspect.signature(factory).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return runtime
    return {k: v for k, v in runtime.items() if k in parameters}


def check_arguments(factory: Callable, params: dict, runtime: dict, what: str, where: str) -> None:
    """Config keys the factory does not take, or that clash with runtime arguments, fail here, before any work."""
    sig = inspect.signature(factory)
    accepts_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values())
    settable = [n for n, p in sig.parameters.items()
                if n not in runtime and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    for key in params:
        if key in runtime:
            raise ConfigError(f"{where}.{key} is set by geoloc at run time, not from config ({what})")
        if key not in settable and not accepts_any:
            raise ConfigError(f"{where}.{key} is not an argument of {what}; its arguments are {settable}")
    missing = [n for n, p in sig.parameters.items() if p.default is p.empty and n not in params and n not in runtime
               and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    if missing:
        raise ConfigError(f"{where} needs {missing} ({what}); set {', '.join(f'{where}.{m}=...' for m in missing)}")


def import_module(spec: str | None, where: str = "module") -> None:
    """Import a plug-in: a dotted module name (on sys.path) or a path to a .py file."""
    if not spec:
        return
    if spec.endswith(".py"):
        path = Path(spec).expanduser().resolve()
        if not path.is_file():
            raise ConfigError(f"{where}.module={spec!r}: no such file ({path})")
        name = f"geoloc_plugin_{path.stem}_{abs(hash(str(path))) % 10**8}"
        if name in sys.modules:
            return
        loader = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(loader)
        sys.modules[name] = module
        try:
            loader.loader.exec_module(module)
        except BaseException:
            del sys.modules[name]
            raise
        return
    try:
        importlib.import_module(spec)
    except ModuleNotFoundError as err:
        raise ConfigError(f"{where}.module={spec!r} cannot be imported ({err}); give a module on sys.path "
                          f"(PYTHONPATH) or a path to a .py file") from None


def _declared(kind: str) -> Kind:
    """The declared kind, its `load` run once; an undeclared kind is a programming error, not a config one."""
    declared = _kinds.get(kind)
    if declared is None:
        raise ValueError(f"component kind {kind!r} is not declared; the declared kinds are {sorted(_kinds)}. The "
                         f"package that builds a kind declares it (registry.declare): import it first")
    if declared.load is not None and kind not in _loaded:
        _loaded.add(kind)
        declared.load()
    return declared


def _stray_hint() -> str:
    """Names registered under kinds that nobody declares: most likely a misspelt kind in a plug-in."""
    strays = {kind: sorted(entries) for kind, entries in _registry.items() if kind not in _kinds and entries}
    return f". Registered under kinds nobody declares (misspelt?): {strays}" if strays else ""


def _as_dict(section: DictConfig | dict | None) -> dict:
    if section is None:
        return {}
    if isinstance(section, DictConfig):
        return OmegaConf.to_container(section, resolve=True)
    return dict(section)


def _origin(fn: Any) -> tuple:
    """Where a factory is defined: a module imported twice (by name and by file path) registers the same one."""
    code = getattr(fn, "__code__", None)
    return (code.co_filename if code else _qualname(fn), getattr(fn, "__qualname__", repr(fn)))


def _qualname(fn: Any) -> str:
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
