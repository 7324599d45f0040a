"""One way to plug in a component: a registry per kind, keyed by the `name` field of its config section.

    @register("loss", "my_loss")
    def my_loss(margin: float = 0.3) -> nn.Module: ...

    # conf/loss/my_loss.yaml (any folder on hydra.searchpath)
    name: my_loss
    module: my_project.losses      # imported before the lookup: a module name or a path to a .py file
    margin: 0.3

`build(kind, section, **runtime)` imports `module` when given, looks `name` up, checks the remaining keys against
the factory's signature and calls it with them plus the runtime arguments the caller supplies (a head gets its
backbone's channels, a loss its descriptor dimension...). An unknown name or argument fails at start-up, naming the
key and the choices. docs/extending.md lists the kinds and what each factory receives and returns.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import sys
from pathlib import Path
from typing import Any, Callable

from omegaconf import DictConfig, OmegaConf

from geoloc.config import ConfigError

#: the kinds of component, and the config section each is read from
KINDS = {
    "dataset": "dataset",
    "backbone": "backbone",
    "head": "head",
    "loss": "loss",
    "sampler": "sampler",
    "optimizer": "optim",
    "segmenter": "task.segmentation",  # task=mmdip's phase-1 network, named by task.segmentation.model
}
#: the arguments geoloc passes a factory of each kind at run time (docs/extending.md); they are not config keys
RUNTIME = {
    "dataset": ("root", "split"),
    "backbone": (),
    "head": ("in_channels", "dim"),
    "loss": ("dim",),
    "optimizer": ("params", "max_epochs"),
    "sampler": ("labels", "batch_size", "seed", "rank", "world_size", "neighbours"),
    "segmenter": ("num_classes",),
}
# the key that names a component, where it is not <section>.name
NAME_KEYS = {"segmenter": "task.segmentation.model"}
# the modules that register geoloc's own components (imported on first lookup)
BUILTIN_MODULES = (
    "geoloc.datasets",
    "geoloc.models.backbones",
    "geoloc.models.heads",
    "geoloc.losses.gms_triplet_loss",
    "geoloc.losses.infonce",
    "geoloc.data.samplers",
    "geoloc.models.optim",
    "geoloc.tasks.mmdip.networks",
)
RESERVED = ("name", "module")

_registry: dict[str, dict[str, Callable]] = {kind: {} for kind in KINDS}
_builtins_loaded = False


def register(kind: str, name: str) -> Callable[[Callable], Callable]:
    """Decorator: make `fn` buildable as `<section>.name=<name>`. Registering a taken name is an error."""
    if kind not in KINDS:
        raise ValueError(f"unknown component kind {kind!r}; the kinds are {list(KINDS)}")

    def add(fn: Callable) -> Callable:
        taken = _registry[kind].get(name)
        if taken is not None and taken is not fn and _origin(taken) != _origin(fn):
            raise ValueError(f"{kind} {name!r} is already registered by {_qualname(taken)}; pick another name")
        _registry[kind][name] = fn
        return fn

    return add


def names(kind: str) -> list[str]:
    _load_builtins()
    return sorted(_registry[kind])


def lookup(kind: str, name: str) -> Callable:
    _load_builtins()
    if name not in _registry[kind]:
        key = NAME_KEYS.get(kind, f"{KINDS[kind]}.name")
        raise ConfigError(f"{key}={name!r} is not a known {kind}; choose one of {names(kind)}, or add one from your "
                          f"own module (docs/extending.md)")
    return _registry[kind][name]


def build(kind: str, section: DictConfig | dict, *, exclude: tuple[str, ...] = (), **runtime: Any) -> Any:
    """Build the `kind` named by `section.name` with the section's other keys (minus `exclude`) plus `runtime`."""
    factory, params, runtime = _resolve(kind, section, exclude, runtime)
    return factory(**params, **runtime)


def with_defaults(kind: str, section: DictConfig | dict) -> dict:
    """`section` with every config key of its factory present: the factory's signature defaults (run-time
    arguments excepted; tuples as lists), overlaid with the section's own values."""
    params = _as_dict(section)
    import_module(params.get("module"), KINDS[kind])
    factory = lookup(kind, params["name"])
    keys = {}
    for key, param in inspect.signature(factory).parameters.items():
        if key in RUNTIME.get(kind, ()) or param.kind not in (param.POSITIONAL_OR_KEYWORD, param.KEYWORD_ONLY):
            continue
        default = None if param.default is param.empty else param.default
        keys[key] = list(default) if isinstance(default, tuple) else default
    named = {k: params[k] for k in RESERVED if k in params}
    return {**named, **keys, **params}


def check(kind: str, section: DictConfig | dict, *, exclude: tuple[str, ...] = (),
          runtime: tuple[str, ...] = ()) -> None:
    """build()'s checks without building: for what is built later (an optimizer needs the network first)."""
    _resolve(kind, section, exclude, dict.fromkeys(runtime))


def _resolve(kind: str, section, exclude: tuple[str, ...], runtime: dict) -> tuple[Callable, dict, dict]:
    """(factory, its config keys, the runtime arguments it takes), checked: the plug-in module imported, the name
    known, every key an argument and every argument without a default given."""
    params = _as_dict(section)
    where = KINDS[kind]
    if "name" not in params:
        raise ConfigError(f"config section '{where}' has no 'name'; choose one of {names(kind)}")
    import_module(params.get("module"), where)
    factory = lookup(kind, params["name"])
    params = {k: v for k, v in params.items() if k not in RESERVED and k not in exclude}
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


def _load_builtins() -> None:
    global _builtins_loaded
    if not _builtins_loaded:
        _builtins_loaded = True
        for module in BUILTIN_MODULES:
            importlib.import_module(module)


def _as_dict(section: DictConfig | dict | None) -> dict:
    if section is None:
        return {}
    if isinstance(section, DictConfig):
        return OmegaConf.to_container(section, resolve=True)
    return dict(section)


def _origin(fn: Callable) -> tuple:
    """Where a factory is defined: a module imported twice (by name and by file path) registers the same one."""
    code = getattr(fn, "__code__", None)
    return (code.co_filename if code else _qualname(fn), getattr(fn, "__qualname__", repr(fn)))


def _qualname(fn: Callable) -> str:
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
