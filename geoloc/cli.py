"""The `geoloc` console script: `geoloc SUBCOMMAND key=value ...` (pyproject [project.scripts]).

Every app is reachable from it:
- train, evaluate, localize, export are the Hydra entry points of the package (geoloc/entry_points.py,
  composing geoloc/conf/), so `geoloc train dataset=cvusa` is `python train.py dataset=cvusa`, and both work from
  an installed wheel;
- the other subcommands are modules with `USAGE` (text) and `main(args) -> exit code`, imported only when named,
  so `geoloc --help` needs no extra; serve, robustness, bench and gallery merge compose their geoloc/conf/ yaml.
"""

from __future__ import annotations

import importlib
import sys

from geoloc.config import ConfigError
from geoloc.entry_points import VERBS

SCRIPTS = {  # name: (the script at a checkout's root that runs the same entry point, what it does)
    "train": ("train.py", "train a task (the embedded default: cross-view on synthetic data)"),
    "evaluate": ("evaluate.py", "score a checkpoint on a split; save or load a gallery"),
    "localize": ("localize.py", "street images against a saved gallery: top-k tiles, position, heading"),
    "export": ("export.py", "a checkpoint's encoders as ONNX files"),
}
SUBCOMMANDS = {  # name: (module, what it does, the pyproject extra it needs)
    "serve": ("geoloc.apps.serve.command", "answer POST /localize and GET /health over HTTP", "serve"),
    "robustness": ("geoloc.apps.robustness", "one table of a checkpoint at each FoV, heading known / unknown, with "
                   "distractors and on another dataset", None),
    "bench": ("geoloc.apps.bench.command", "many checkpoints x test sets x FoV / heading protocols in one table, "
              "beside the published figures", None),
    "gallery": ("geoloc.apps.gallery.command", "merge SHARD_DIR... | append GALLERY_DIR PART_DIR... out=DIR: one gallery from shard jobs, or grown by new references", "faiss"),
    "list": ("geoloc.apps.components.listing", "every registered component (dataset, backbone, loss...) and its "
             "config keys", None),
}


def usage() -> str:
    lines = ["usage: geoloc SUBCOMMAND key=value ...   (geoloc SUBCOMMAND --help for its keys)", "", "subcommands:"]
    lines += [f"  {name:12s}{what} (python {script})" for name, (script, what) in SCRIPTS.items()]
    lines += [f"  {name:12s}{what}" + (f" (pip install -e \".[{extra}]\")" if extra else "")
              for name, (_, what, extra) in SUBCOMMANDS.items()]
    return "\n".join(lines)


def run_script(name: str, args: list[str]) -> int:
    """Run the entry point `name` as `python <script> args` would; its exit status."""
    argv = sys.argv
    sys.argv = [f"geoloc {name}", *args]
    try:
        VERBS[name]()
    except SystemExit as exit_:
        if isinstance(exit_.code, str):  # a refusal's one line (launch/refusal.py)
            print(exit_.code, file=sys.stderr)
            return 1
        return exit_.code if isinstance(exit_.code, int) else 0
    finally:
        sys.argv = argv
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    name, args = argv[0], argv[1:]
    if name in SCRIPTS:
        return run_script(name, args)
    if name not in SUBCOMMANDS:
        print(f"geoloc: unknown subcommand {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module_name, _, extra = SUBCOMMANDS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name and err.name.split(".")[0] in ("geoloc",):
            raise
        print(f"geoloc {name} needs the package {err.name!r}: pip install -e \".{f'[{extra}]' if extra else ''}\"",
              file=sys.stderr)
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
