"""The `geoloc` console script: `geoloc SUBCOMMAND key=value ...` (pyproject [project.scripts]).

Each subcommand is a module with `USAGE` (text) and `main(args) -> exit code`; it is imported only when named,
so `geoloc --help` works without the optional extras a subcommand needs.
"""

from __future__ import annotations

import importlib
import sys

from omegaconf import OmegaConf

from geoloc.config import ConfigError, checked

SUBCOMMANDS = {  # name: (module, what it does, the pyproject extra it needs)
    "serve": ("geoloc.apps.serve.command", "answer POST /localize and GET /health over HTTP", "serve"),
}


def usage() -> str:
    lines = ["usage: geoloc SUBCOMMAND key=value ...   (geoloc SUBCOMMAND --help for its keys)", "", "subcommands:"]
    lines += [f"  {name:8s}{what} (pip install -e \".[{extra}]\")" for name, (_, what, extra) in SUBCOMMANDS.items()]
    return "\n".join(lines)


def parse_keys(args: list[str], schema: type, command: str):
    """key=value arguments (as Hydra takes them) -> a `schema` dataclass; a bad one raises ConfigError."""
    for arg in args:
        key, sep, _ = arg.partition("=")
        if not sep or not key:
            raise ConfigError(f"'{arg}' is not key=value: geoloc {command} takes its settings as key=value")
    return checked(OmegaConf.from_dotlist(args), schema, command)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    name, args = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"geoloc: unknown subcommand {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module_name, _, extra = SUBCOMMANDS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name and err.name.split(".")[0] in ("geoloc",):
            raise
        print(f"geoloc {name} needs the package {err.name!r}: pip install -e \".[{extra}]\"", file=sys.stderr)
        return 1
    if any(arg in ("-h", "--help") for arg in args):
        print(module.USAGE)
        return 0
    try:
        return module.main(args)
    except ConfigError as err:
        print(f"geoloc {name}: {err}\n\n{module.USAGE}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
