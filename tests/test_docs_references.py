"""The docs name only files, modules and functions that exist, and point nowhere outside the project.

What is read: README.md, docs/*.md and benchmarks/README.md (paragraph by paragraph), the comments of
geoloc/conf/**/*.yaml, and the docstrings and comments of geoloc/**/*.py, tools/*.py, benchmarks/*.py, data_prep/*.py and
the root scripts.

The rules. Each resolves a reference one way only, so that a correct tree passes with nothing to allow:

1. Paths: a token that starts with geoloc/, tests/, docs/, conf/, benchmarks/, tools/ or data_prep/ must exist,
   as a file or a folder (with a glob `*`: match something). Skipped: a path with a placeholder (`<date>`, `...`,
   `{a,b}`, `$X`, or an upper-case segment such as DIR, RUN or SHARD_i), URLs, and paths of other repositories or
   datasets (they do not start with one of these folders; an example of the reader's own conf dir is written
   my_conf/...).
2. A markdown link `[text](target)`, not a URL, must exist relative to the doc.
3. `geoloc.a.b...`: the longest prefix that is a module or package must be followed by at most two names: the first
   bound at its top level (def, class, assignment, import), the second, when the first is a class, in the class.
   Format tags such as `geoloc.gallery/1` are not module names.
4. `path.py:name` and pytest ids `path.py::name`: the file must define `name` (`Class.method` in the class;
   `name...` as a prefix). A bare `test_x.py::name` is resolved under tests/ when exactly one file has that name;
   in docs/testing.md, which speaks only of this project's tests, a bare `test_x.py` must be one file under tests/.
   Elsewhere a bare `x.py` is not checked: the docs cite other repositories' scripts (VIGOR's `dataloader.py`).
5. `` `module.name` ``, where `module` is the file name of exactly one module of geoloc/ and neither a config key
   (`trainer.device`, `gallery.kind`) nor a key of a dict literal in geoloc/ (a JSON record's field:
   `calibration.within_5m`), and `name` is not a file suffix (`gallery.json`): `module` must bind `name` at its top
   level. In a .py file, `module` may also be a module the file imports, and a parameter or variable of the file
   (`task.model`) is an object, not checked.
6. `` `name()` `` must be a def, class, parameter or variable of the project's code (geoloc, tests, tools,
   benchmarks, data_prep, root scripts), a builtin, a torch function or a method of torch.Tensor, torch.nn.Module
   or torch.optim.Optimizer.
7. `` `snake_case_name` `` (one underscore or more) and `` `CamelCaseName` `` (capital, lower case, capital...) must
   occur in the code (a name, attribute, argument, keyword, import, a word of a string constant other than a
   docstring, or an f-string's shape: `whole_tile_within_5m`), in conf/ (keys, values, file names) or in
   pyproject.toml.
   Rules 5 to 7 skip a name that follows a possessive or a file name, the name of another project
   (CCVPE's `ori_noise`, `train_SAFA.py` `validate_top`, hydra-submitit-launcher's `SlurmQueueConf`).
8. Nothing points outside the project (OUTSIDE): not into the folder shared beside the checkout, not to the
   workplace's design or style files, not to an absolute path of the machine the docs were written on.

Every list of gallery kinds (four or more kind names, starting with flat) names every kind the registry has
(geoloc.eval.index_kinds.KINDS). The self-tests feed the checkers one broken reference of each kind, and real
references and placeholders that must pass.
"""

from __future__ import annotations

import ast
import builtins
import io
import re
import tokenize
from functools import lru_cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TOP = ("geoloc", "tests", "docs", "conf", "benchmarks", "tools", "data_prep")


# --- the text to check -----------------------------------------------------------------------------------------


def sources() -> list[Path]:
    md = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), REPO / "benchmarks" / "README.md"]
    yaml = sorted((REPO / "geoloc" / "conf").rglob("*.yaml"))
    py = [*sorted((REPO / "geoloc").rglob("*.py")), *sorted(REPO.glob("*.py"))]
    for folder in ("tools", "benchmarks", "data_prep"):
        py += sorted((REPO / folder).glob("*.py"))
    return md + yaml + py


def fragments(path: Path, text: str) -> list[tuple[int, str]]:
    """(first line, text) pieces of a source that are prose: a markdown file's paragraphs, comments, docstrings."""
    if path.suffix == ".md":
        out, start = [], 1
        for block in re.split(r"(\n[ \t]*\n)", text):
            if block.strip() and not block.isspace():
                out.append((start, block))
            start += block.count("\n")
        return out
    if path.suffix == ".yaml":
        return [(i, line.split("#", 1)[1]) for i, line in enumerate(text.splitlines(), 1) if "#" in line]
    out: list[tuple[int, str]] = []
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT:
            if out and out[-1][0] + out[-1][1].count("\n") == tok.start[0] - 1:  # a comment block is one piece
                out[-1] = (out[-1][0], out[-1][1] + "\n" + tok.string)
            else:
                out.append((tok.start[0], tok.string))
    for node in nodes(path):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                    and isinstance(first.value.value, str)):
                out.append((first.lineno, first.value.value))
    return out


# --- what the project defines ----------------------------------------------------------------------------------

@lru_cache(maxsize=None)
def tree(file: Path) -> ast.Module:
    return ast.parse(file.read_text(encoding="utf-8"))


@lru_cache(maxsize=None)
def nodes(file: Path) -> tuple[ast.AST, ...]:
    """Every node of a file's tree, walked once."""
    return tuple(ast.walk(tree(file)))


def defined(body: list[ast.stmt]) -> dict[str, ast.AST]:
    """Names bound by a module's or a class's body (defs, classes, assignments, imports), with their node."""
    names: dict[str, ast.AST] = {}
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names[node.name] = node
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                for n in ast.walk(target):
                    if isinstance(n, ast.Name):
                        names[n.id] = node
        elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name):
            names[node.target.id] = node
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                names[(alias.asname or alias.name).split(".")[0]] = node
        elif isinstance(node, (ast.If, ast.Try, ast.With)):
            inner = node.body + getattr(node, "orelse", []) + getattr(node, "finalbody", [])
            for handler in getattr(node, "handlers", []):
                inner += handler.body
            names.update(defined(inner))
    return names


def has_name(file: Path, dotted: str) -> bool:
    """Whether `file` defines `name` or `Class.member`."""
    first, _, member = dotted.partition(".")
    node = defined(tree(file).body).get(first)
    if node is None or not member:
        return node is not None
    if not isinstance(node, ast.ClassDef):
        return True  # an attribute of an instance or an imported object: not followed further
    return member in defined(node.body) or any(  # a dataclass field or an attribute set in a method
        isinstance(n, ast.Attribute) and n.attr == member and isinstance(n.ctx, ast.Store) for n in ast.walk(node))


def module_file(parts: list[str]) -> Path | None:
    base = REPO.joinpath(*parts)
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    return base.with_suffix(".py") if base.with_suffix(".py").is_file() else None


def code_files() -> list[Path]:
    """The project's Python files, this one left out (its fake references must not count as names)."""
    files = [*REPO.glob("*.py")] + [f for top in TOP if (REPO / top).is_dir() for f in (REPO / top).rglob("*.py")]
    return [f for f in files if f.resolve() != Path(__file__).resolve()]


def docstrings(module: Path) -> set[int]:
    """The ids of a module's docstring nodes: prose, not names the code uses."""
    return {id(node.body[0].value) for node in nodes(module)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body
            and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}


@lru_cache(maxsize=None)
def geoloc_modules() -> dict[str, list[Path]]:
    """File name (without .py) -> the modules of geoloc/ with that name."""
    out: dict[str, list[Path]] = {}
    for file in (REPO / "geoloc").rglob("*.py"):
        if file.name != "__init__.py":
            out.setdefault(file.stem, []).append(file)
    return out


@lru_cache(maxsize=None)
def callables() -> frozenset[str]:
    """What `name()` may name: the project's defs, classes and callable parameters or variables, builtins, torch."""
    import torch

    names = set(dir(builtins)) | set(dir(torch)) | set(dir(torch.Tensor)) | set(dir(torch.nn.Module))
    names |= set(dir(torch.optim.Optimizer))
    for file in code_files():
        for node in nodes(file):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, ast.arg):
                names.add(node.arg)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                names.add(node.id)
    return frozenset(names)


@lru_cache(maxsize=None)
def known_words() -> tuple[frozenset[str], tuple[re.Pattern, ...]]:
    """Every identifier the project's code, configs and pyproject.toml use (names, attributes, arguments, keywords,
    the words of string constants; conf/'s keys, values and file names), and the f-strings' shapes
    (`f"whole_tile_within_{t}m"` -> whole_tile_within_\\w+m)."""
    words = set(dir(builtins)) | config_keys() | {f.stem for f in code_files()}
    shapes = []
    for file in code_files():
        prose = docstrings(file)
        for node in nodes(file):
            if id(node) in prose:
                continue
            for field in ("name", "id", "attr", "arg"):
                if isinstance(getattr(node, field, None), str):
                    words.add(getattr(node, field))
            if isinstance(node, ast.alias):
                words.update(re.findall(r"\w+", node.name))
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                words.update(re.findall(r"\w+", node.value))
            elif isinstance(node, ast.JoinedStr):
                if isinstance(node.values[0], ast.Constant) and "_" in node.values[0].value:  # a name's shape
                    shape = "".join(re.escape(v.value) if isinstance(v, ast.Constant) else r"\w+" for v in node.values)
                    shapes.append(re.compile(shape))
    for file in [*(REPO / "geoloc" / "conf").rglob("*.yaml"), REPO / "pyproject.toml"]:
        text = "\n".join(line.split("#", 1)[0] for line in file.read_text(encoding="utf-8").splitlines())
        words.update(re.findall(r"\w+", text))
    return frozenset(words), tuple(shapes)


@lru_cache(maxsize=None)
def config_keys() -> frozenset[str]:
    """Every key, group and file name of conf/, and the `@name` packages of its defaults: config, not code."""
    keys = {p.stem for p in (REPO / "geoloc" / "conf").rglob("*")}
    for file in (REPO / "geoloc" / "conf").rglob("*.yaml"):
        for line in file.read_text(encoding="utf-8").splitlines():
            line = line.split("#", 1)[0]
            keys.update(k.split("/")[-1] for k in re.findall(r"^\s*-?\s*/?([\w/]+?)(?:@[\w.]+)?\s*:", line))
            keys.update(re.findall(r"@(\w+)", line))
    return frozenset(keys)


@lru_cache(maxsize=None)
def record_keys() -> frozenset[str]:
    """The string keys of geoloc's dict literals: fields of the JSON records it writes (`calibration.within_5m`)."""
    keys = set()
    for file in (REPO / "geoloc").rglob("*.py"):
        for node in nodes(file):
            if isinstance(node, ast.Dict):
                keys.update(k.value for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str))
    return frozenset(keys)


@lru_cache(maxsize=None)
def bound_names(file: Path) -> frozenset[str]:
    """The parameters and variables of a .py file: `task.model` there is an object's attribute, not a module's."""
    return frozenset(node.arg if isinstance(node, ast.arg) else node.id for node in nodes(file)
                     if isinstance(node, ast.arg) or (isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store)))


@lru_cache(maxsize=None)
def imported_modules(file: Path) -> dict[str, Path]:
    """The names a .py file binds to a module of this project."""
    out = {}
    for node in nodes(file):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                target = module_file([*node.module.split("."), alias.name])
                if target is not None:
                    out[alias.asname or alias.name] = target
        elif isinstance(node, ast.Import):
            for alias in node.names:
                target = module_file(alias.name.split("."))
                if target is not None and alias.asname:
                    out[alias.asname] = target
    return out


# --- the checker -----------------------------------------------------------------------------------------------

PATH = re.compile(r"(?<![\w./~:-])((?:%s)/[\w.\-/*<>{},$]*)" % "|".join(TOP))
LINK = re.compile(r"\]\(([^)\s]+)\)")
DOTTED = re.compile(r"(?<![\w./-])geoloc(?:\.\w+)+(?![\w/-])")
FILE_FUNC = re.compile(r"(?<![\w./-])((?:[\w-]+/)*\w+\.py)(::?)([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)?)(\.\.\.)?")
BARE_TEST = re.compile(r"(?<![\w./:-])(test_\w+\.py)(?![\w/])")
TICKED = re.compile(r"`+([^`\n]+?)`+")
MOD_ATTR = re.compile(r"([A-Za-z_]\w*)\.([A-Za-z_]\w*)(\(.*\))?")
CALL = re.compile(r"([A-Za-z_]\w*)\(\)")
IDENTIFIER = re.compile(r"[a-z][a-z0-9]*(?:_[a-z0-9]+)+|[A-Z][a-z0-9]+(?:[A-Z][a-z0-9]*)+")
OUTSIDE = re.compile(r"\.\./shared\b|\bDESIGN\.md\b|\bSTYLE\.md\b|(?<![\w.])/work/")  # see rule 8
FILE_SUFFIXES = {"py", "md", "json", "jsonl", "csv", "pt", "yaml", "yml", "png", "jpg", "txt", "onnx", "npy", "mat",
                 "log", "html", "toml", "lock", "pth", "tar", "gz", "zip"}


def placeholder(path: str) -> bool:
    return bool(re.search(r"[<>{}$]|\.\.\.|(^|/)[A-Z][A-Z0-9_]*(/|$|\.)", path))


def check_path(path: str) -> str | None:
    path = path.rstrip(".,:;")
    if placeholder(path):
        return None
    if "*" in path:
        return None if any(REPO.glob(path)) else f"no file matches {path}"
    return None if (REPO / path).exists() else f"no such file or folder: {path}"


def check_dotted(name: str) -> str | None:
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        file = module_file(parts[:n])
        if file is not None:
            rest = ".".join(parts[n:])
            if not rest or len(parts) - n > 2:
                return None  # the module itself, or an attribute of an attribute (not followed)
            return None if has_name(file, rest) else f"{'.'.join(parts[:n])} has no {rest}"
    return f"no module {name}"


def find_test_file(name: str) -> Path | None:
    hits = list((REPO / "tests").rglob(name))
    return hits[0] if len(hits) == 1 else None


def check_file_func(path: str, name: str, prefix: bool) -> str | None:
    if placeholder(path):
        return None
    file = REPO / path if "/" in path else find_test_file(path)
    if file is None or not file.is_file():
        return f"no such file: {path}" if "/" in path or path.startswith("test_") else None  # else another repo's
    if prefix:  # test_a_gallery_counts_...
        names = [n.name for n in nodes(file) if isinstance(n, (ast.FunctionDef, ast.ClassDef))]
        return None if any(n.startswith(name) for n in names) else f"{path} has no {name}..."
    return None if has_name(file, name) else f"{path} has no {name}"


def check_ticked(token: str, source: Path | None) -> str | None:
    call = CALL.fullmatch(token)
    if call:
        return None if call.group(1) in callables() else f"no function or class {call.group(1)}"
    if IDENTIFIER.fullmatch(token):
        words, shapes = known_words()
        if token in words or any(s.fullmatch(token) for s in shapes):
            return None
        return f"no name {token} in the code or the configs"
    match = MOD_ATTR.fullmatch(token)
    if not match or match.group(2) in FILE_SUFFIXES:
        return None
    module, name = match.group(1), match.group(2)
    file = None
    if source is not None and source.suffix == ".py":
        file = imported_modules(source).get(module)
        if file is None and module in bound_names(source):
            return None
    if (file is None and module not in config_keys() and module not in record_keys()
            and len(geoloc_modules().get(module, [])) == 1):
        file = geoloc_modules()[module][0]
    if file is None or file.name == "__init__.py":
        return None
    return None if has_name(file, name) else f"{file.relative_to(REPO)} has no {name}"


def check_text(text: str, source: Path | None = None) -> list[tuple[int, str]]:
    """The broken references in one piece of prose: (offset in `text`, message)."""
    found = [(m.start(), f"points outside the project: {m.group(0)}") for m in OUTSIDE.finditer(text)]
    found += [(m.start(), check_path(m.group(1))) for m in PATH.finditer(text)]
    if source is not None and source.suffix == ".md":
        for m in LINK.finditer(text):
            target = m.group(1).split("#", 1)[0]
            if target and not re.match(r"[a-z]+:", target) and not (source.parent / target).exists():
                found.append((m.start(), f"broken link: {target}"))
    found += [(m.start(), check_dotted(m.group(0))) for m in DOTTED.finditer(text)]
    found += [(m.start(), check_file_func(m.group(1), m.group(3), bool(m.group(4)))) for m in FILE_FUNC.finditer(text)]
    if source is not None and source.name == "testing.md":
        found += [(m.start(), None if find_test_file(m.group(1)) else f"no test file {m.group(1)} under tests/")
                  for m in BARE_TEST.finditer(text)]
    for m in TICKED.finditer(text):
        # CCVPE's `ori_noise`, `train_SAFA.py` `validate_top`: another project's name
        if not re.search(r"('s|\.py`)\s*$", text[:m.start()]):
            found.append((m.start(), check_ticked(m.group(1).strip(), source)))
    return [(at, message) for at, message in found if message]


def broken_references() -> list[str]:
    out = []
    for path in sources():
        for line, text in fragments(path, path.read_text(encoding="utf-8")):
            out += [f"{path.relative_to(REPO)}:{line + text[:at].count(chr(10))}: {message}"
                    for at, message in check_text(text, path)]
    return out


# --- the tests -------------------------------------------------------------------------------------------------

def test_every_reference_in_the_docs_exists():
    broken = broken_references()
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize("kind, line", [
    ("path", "see tests/launch/test_no_such_file.py"),
    ("link", "see [the guide](no_such_guide.md)"),
    ("module", "from `geoloc.engine.no_such_module`"),
    ("function", "`geoloc.engine.checkpoint.no_such_function` does it"),
    ("file function", "geoloc/apps/query.py:no_such_function"),
    ("module.function", "`scoring.no_such_function` ranks"),
    ("call", "`no_such_function_anywhere()` checks it"),
    ("name", "`check_no_such_query` runs on the header"),
    ("class", "the default in `NoSuchLossConfig`"),
    ("pytest id", "test_scoring.py::test_no_such_test"),
    ("outside", "the conventions are in " + "/".join(["..", "shared", "conventions.md"])),
    ("outside", "as the workplace's " + "STYLE" + ".md says"),
])
def test_the_checker_reports_each_kind_of_drift(kind, line):
    assert check_text(line, REPO / "docs" / "fake.md"), kind


def test_the_checker_passes_real_references_and_placeholders():
    fine = ("tests/launch/test_resume.py, [usage](usage.md), `geoloc.engine.checkpoint`, geoloc.eval.index_kinds.KINDS, "
            "geoloc/apps/localize/command.py:localize, `scoring.rank`, `config_nodes()`, `trainer.device`, "
            "`gallery.json`, outputs/crossview/<date>/best.pt, geoloc/conf/experiment/*.yaml, gallery.save=DIR/SHARD_i, "
            "VIGOR's `dataloader.py`, CCVPE's `ori_noise`, https://github.com/x/y/tests/z.py, `heading_steps`")
    assert check_text(fine, REPO / "docs" / "fake.md") == []


def kind_lists(text: str, kinds: tuple[str, ...]) -> list[tuple[int, set[str]]]:
    """The lists of gallery kinds in a piece of prose: runs of four or more kind names that start with `flat` (as the
    registry does), each at most about 30 characters or one line break from the next (`flat (exact) | ivfpq | ...`,
    ``"flat"`` (exact) or, with FAISS, ``"ivfpq"``); a subset that leaves flat out or names it last is not a list."""
    word = "|".join(sorted(kinds, key=len, reverse=True))
    sep = r"(?:\W[^\n]{0,30}?\W|\W*\n\W*)"
    runs = re.finditer(rf"\bflat\b(?:{sep}\b(?:{word})\b)+", text)
    found = [(run.start(), set(re.findall(rf"\b(?:{word})\b", run.group(0)))) for run in runs]
    return [(at, names) for at, names in found if len(names) >= 4]


def test_every_list_of_gallery_kinds_names_them_all():
    from geoloc.eval.index_kinds import KINDS

    assert kind_lists("kind: flat (exact) | ivfpq | pq_refine | hnsw", KINDS) == [(6, {"flat", "ivfpq", "pq_refine",
                                                                                      "hnsw"})]
    assert kind_lists("the trained kinds: pq_sq8, pq_refine, ivfpq_refine, ivfpq; flat needs none", KINDS) == []
    stale = kind_lists("``\"flat\"`` (exact) or, with FAISS, ``\"ivfpq\"``, ``\"pq_refine\"``, ``\"ivfpq_refine\"``,\n"
                       "    ``\"hnsw\"``", KINDS)
    assert [names for _, names in stale] == [{"flat", "ivfpq", "pq_refine", "ivfpq_refine", "hnsw"}]
    short = []
    for path in sources():
        for line, text in fragments(path, path.read_text(encoding="utf-8")):
            short += [f"{path.relative_to(REPO)}:{line + text[:at].count(chr(10))}: lacks {sorted(set(KINDS) - names)}"
                      for at, names in kind_lists(text, KINDS) if names != set(KINDS)]
    assert not short, "\n".join(short)
