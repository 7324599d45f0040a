"""`geoloc list [KIND ...]`: every registered kind of component, each name in it, and the config keys it takes.

What a reader would otherwise piece together from the registrations scattered over the packages: which losses,
backbones, samplers... exist, which config section picks one (`loss.name=...`), which keys each takes with their
defaults, and which arguments geoloc passes at run time instead (never config keys)."""

from __future__ import annotations

import importlib
import inspect

from geoloc import registry
from geoloc.config import ConfigError

USAGE = """usage: geoloc list [KIND ...]

Every registered component kind (or only the KINDs named), each name in it with the function or class that builds
it and the config keys it takes (key=default). Components from your own module appear once it is imported
(section.module=...; docs/extending.md)."""

# the packages that own the built-in kinds: importing them registers every built-in (their __init__ files)
OWNERS = ("geoloc.tasks.crossview.crossview_run", "geoloc.tasks.mmdip.pipeline")


def keys(factory, runtime: tuple[str, ...]) -> list[str]:
    """`key=default` for each config key of `factory` (a function or class); `key=???` where it has no default."""
    try:
        parameters = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):  # a module (a task) or a builtin: no signature to read
        return []
    out = []
    for p in parameters:
        if p.name in runtime or p.name in registry.RESERVED or p.kind not in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
            continue
        out.append(f"{p.name}={'???' if p.default is p.empty else p.default!r}")
    return out


def describe(kind: str) -> list[str]:
    """The lines of one kind: its section and run-time arguments, then one line per name."""
    declared = registry.kinds()[kind]
    runtime = f"; geoloc passes {', '.join(declared.runtime)}" if declared.runtime else ""
    lines = [f"{kind}  ({declared.name_key}=NAME{runtime})"]
    for name in registry.names(kind):
        factory = registry.lookup(kind, name)
        where = getattr(factory, "__module__", None) or getattr(factory, "__name__", "")
        built = f"{where}.{getattr(factory, '__qualname__', '')}".rstrip(".")
        lines.append(f"  {name:17s} {built}")
        settable = keys(factory, declared.runtime)
        if settable:
            lines.append(f"  {'':18s}{'  '.join(settable)}")
    return lines


def main(args: list[str]) -> int:
    for owner in OWNERS:
        importlib.import_module(owner)
    known = registry.kinds()
    unknown = [a for a in args if a not in known]
    if unknown:
        raise ConfigError(f"unknown kind(s) {unknown}: the kinds are {sorted(known)}")
    for kind in args or list(known):
        print("\n".join(describe(kind)) + "\n")
    return 0
