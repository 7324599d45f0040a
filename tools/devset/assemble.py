"""Assemble geoloc's real dev set (docs/devset.md) from the public files that tools/devset/manifest.json names.

    python tools/devset/assemble.py OUT                      # downloads from raw.githubusercontent.com
    python tools/devset/assemble.py OUT --mirror DIR         # reads local bare git copies: DIR/<owner>+<name>/...

OUT must lie outside this repository and must not be a non-empty folder. Every file's bytes are checked against
the manifest's sha256 before use; a mismatch stops the assembly and names the file. The set is for evaluation
only: no kind gets a train split, so a training run pointed at it is refused by the reader.

Each kind becomes a folder of OUT in a layout one of geoloc's readers takes:
- cvusa_like -> OUT/cvusa_like, CVUSA's layout (`dataset=cvusa`, split val): bingmap/19/N.jpg,
  streetview/panos/N.jpg, splits/val-19zl.csv (two columns; no annotations are shipped);
- cvact_like, vigor_like -> OUT/<kind>, CVACT's layout (`dataset=cvact`, split val): ACT_data.mat (panoIds and
  valSet.valInd only), ANU_data_small/streetview/<id>_grdView.jpg and
  ANU_data_small/satview_polish/<id>_satView_polish.jpg;
- other -> OUT/other, the folder layout (`dataset=folder`, split all, query_view image): queries/, tiles/ and
  queries.csv / tiles.csv whose positions are placeholders 1 km apart that encode only which tile is whose.
OUT/<kind>/pairs.csv says where each assembled pair came from; OUT/README.txt gives each gallery's chance level.
Conversions are the manifest's, per file: `copy` (bytes unchanged, JPEG only) or `jpeg` (OpenCV decode, optional
crop [x, y, width, height], then optional resize [width, height] by pixel-area averaging, JPEG quality 95), so the
same OpenCV build gives the same bytes.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from geoloc.synthetic.layouts import mat_bytes, write_bytes

REPO = Path(__file__).resolve().parents[2]
MANIFEST = Path(__file__).resolve().parent / "manifest.json"
RAW_URL = "https://raw.githubusercontent.com/{repository}/{commit}/{path}"
KINDS = ("cvusa_like", "cvact_like", "vigor_like", "other")
LAYOUTS = {"cvusa_like": "cvusa", "cvact_like": "cvact", "vigor_like": "cvact", "other": "folder"}
ROLES = ("query", "reference")
FIELDS = ("kind", "pair", "role", "repository", "commit", "path", "sha256", "licence", "conversion", "source")
JPEG_QUALITY = 95
PLACE_SPACING_M = 1000.0  # the folder layout's placeholder positions: one place every kilometre along a line
HEX40, HEX64 = re.compile(r"[0-9a-f]{40}"), re.compile(r"[0-9a-f]{64}")
EVALUATE = {"cvusa": "dataset=cvusa dataset.root={root}",
            "cvact": "dataset=cvact dataset.root={root}",
            "folder": "dataset=folder dataset.root={root} dataset.split=all dataset.query_view=image "
                      "dataset.tile_extent_m=<any, the positions are placeholders>"}


# -- the manifest -------------------------------------------------------------------------------------------------
def load_manifest(path: Path) -> list[dict]:
    """The manifest's file entries, each checked (manifest_problems); the first problem is raised naming it."""
    try:
        entries = json.loads(Path(path).read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"manifest {path} is not readable as JSON with a 'files' list ({err}); restore it from the "
                         "repository (tools/devset/manifest.json)") from None
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"manifest {path}: 'files' must be a non-empty list of file entries")
    problems = manifest_problems(entries)
    if problems:
        raise ValueError(f"manifest {path}: {problems[0]} ({len(problems)} problem(s) in all)")
    return entries


def manifest_problems(entries: list) -> list[str]:
    """What is wrong with the entries, one line each, empty when nothing: fields, hex digests, kinds, roles, and
    pairs that lack their query or reference or have two of one."""
    problems = []
    for i, e in enumerate(entries):
        where = f"entry {i} ({e.get('pair', '?')} {e.get('role', '?')})" if isinstance(e, dict) else f"entry {i}"
        if not isinstance(e, dict):
            problems.append(f"{where} is not an object")
            continue
        missing = [f for f in FIELDS if f not in e]
        if missing:
            problems.append(f"{where} lacks {missing}")
            continue
        if not HEX40.fullmatch(str(e["commit"])):
            problems.append(f"{where}: commit {e['commit']!r} is not a full 40-hex commit")
        if not HEX64.fullmatch(str(e["sha256"])):
            problems.append(f"{where}: sha256 {e['sha256']!r} is not 64 lower-case hex digits")
        if e["kind"] not in KINDS:
            problems.append(f"{where}: kind {e['kind']!r} is not one of {list(KINDS)}")
        if e["role"] not in ROLES:
            problems.append(f"{where}: role {e['role']!r} is not one of {list(ROLES)}")
        if not str(e["path"]).strip() or str(e["path"]).startswith("/"):
            problems.append(f"{where}: path {e['path']!r} is not a path inside the repository")
        if not str(e["licence"]).strip():
            problems.append(f"{where}: licence is empty (write 'none' for a repository without one)")
        problems += conversion_problems(e["conversion"], where)
    problems += pair_problems([e for e in entries if isinstance(e, dict) and "pair" in e and "role" in e])
    return problems


def conversion_problems(conversion, where: str) -> list[str]:
    if not isinstance(conversion, dict) or conversion.get("format") not in ("copy", "jpeg"):
        return [(f"{where}: conversion must be {{'format': 'copy' | 'jpeg', 'crop': null | [x, y, w, h], "
                 "'resize': null | [w, h]}")]
    problems = []
    for key, size in (("crop", 4), ("resize", 2)):
        value = conversion.get(key)
        if value is None:
            continue
        if conversion["format"] == "copy":
            problems.append(f"{where}: {key} needs conversion format 'jpeg' ('copy' keeps the bytes)")
        elif not (isinstance(value, list) and len(value) == size and all(type(v) is int for v in value)
                  and all(v >= 0 for v in value) and all(v > 0 for v in value[-2:])):
            problems.append(f"{where}: {key} {value!r} must be "
                            f"{'[x, y, width, height]' if key == 'crop' else '[width, height]'}: whole pixels, "
                            "width and height > 0")
    return problems


def pair_problems(entries: list[dict]) -> list[str]:
    """Each pair id once per role, one kind per pair."""
    roles, kinds = {}, {}
    for e in entries:
        roles.setdefault(e["pair"], []).append(e["role"])
        kinds.setdefault(e["pair"], set()).add(e.get("kind"))
    problems = [f"pair {p} has roles {sorted(r)}; it needs exactly one query and one reference"
                for p, r in roles.items() if sorted(r) != sorted(ROLES)]
    return problems + [f"pair {p} mixes kinds {sorted(map(str, k))}" for p, k in kinds.items() if len(k) > 1]


def pairs_by_kind(entries: list[dict]) -> dict[str, list[tuple[dict, dict]]]:
    """{kind: [(query entry, reference entry), ...]} in the manifest's order of pairs."""
    out: dict[str, list] = {}
    seen = {}
    for e in entries:
        seen.setdefault(e["pair"], {})[e["role"]] = e
    for by_role in seen.values():
        out.setdefault(by_role["query"]["kind"], []).append((by_role["query"], by_role["reference"]))
    return {kind: out[kind] for kind in KINDS if kind in out}


# -- where the bytes come from -------------------------------------------------------------------------------------
class MirrorSource:
    """Bare (or working-tree) git copies under one folder, one per repository: DIR/<owner>+<name>/ holding the git
    directory itself or one level below it (the fetch tool's DIR/<owner>+<name>/repo)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise FileNotFoundError(f"--mirror {self.folder} is not a folder; give the folder that holds "
                                    "<owner>+<name>/ copies of the repositories")
        self.gitdirs: dict[str, Path] = {}

    def gitdir(self, repository: str) -> Path:
        if repository not in self.gitdirs:
            base = self.folder / repository.replace("/", "+")
            found = [d for d in (base, *sorted(base.glob("*")), *sorted(base.glob("*/.git")))
                     if d.is_dir() and (d / "HEAD").is_file() and (d / "objects").is_dir()]
            if not found:
                raise FileNotFoundError(f"repository {repository} is not in the mirror: no git directory at {base} "
                                        f"or one level below it; fetch {repository} into {self.folder}, or leave "
                                        "out --mirror to download")
            self.gitdirs[repository] = found[0]
        return self.gitdirs[repository]

    def read(self, entry: dict) -> bytes:
        gitdir = self.gitdir(entry["repository"])
        run = subprocess.run(["git", f"--git-dir={gitdir}", "show", f"{entry['commit']}:{entry['path']}"],
                             capture_output=True, check=False)
        if run.returncode:
            raise FileNotFoundError(f"{entry['repository']} {entry['commit']}:{entry['path']} cannot be read from "
                                    f"{gitdir}: {run.stderr.decode(errors='replace').strip()}; the mirror lacks "
                                    "that commit or path: fetch the repository again")
        return run.stdout


class WebSource:
    """The files as GitHub serves them at the pinned commit."""

    def __init__(self, timeout_s: float = 60.0):
        self.timeout_s = timeout_s

    def read(self, entry: dict) -> bytes:
        url = RAW_URL.format(repository=entry["repository"], commit=entry["commit"],
                             path=urllib.parse.quote(entry["path"], safe="/"))
        try:
            with urllib.request.urlopen(url, timeout=self.timeout_s) as reply:
                return reply.read()
        except (urllib.error.URLError, OSError) as err:
            raise ConnectionError(f"cannot download {url} ({err}); check the network, or fetch the repository and "
                                  "pass --mirror DIR") from None


def checked_bytes(source, entry: dict) -> bytes:
    """The entry's file, refused unless its sha256 is the manifest's."""
    data = source.read(entry)
    got = hashlib.sha256(data).hexdigest()
    if got != entry["sha256"]:
        raise ValueError(f"sha256 mismatch for {entry['repository']} {entry['commit'][:12]}:{entry['path']} (pair "
                         f"{entry['pair']}, {entry['role']}): the manifest says {entry['sha256']}, the file has {got}. "
                         "The source changed or the copy is damaged: nothing past this file was assembled; check "
                         "the source, and update the manifest only after looking at the new file")
    return data


def converted(data: bytes, entry: dict) -> bytes:
    """The bytes to write (always a JPEG), by the entry's conversion."""
    conversion, where = entry["conversion"], f"{entry['repository']}:{entry['path']}"
    if conversion["format"] == "copy":
        if not data.startswith(b"\xff\xd8"):
            raise ValueError(f"{where} is not a JPEG, so it cannot be copied as one: give it conversion "
                             "format 'jpeg' in the manifest")
        return data
    import cv2
    import numpy as np

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"{where}: OpenCV cannot decode it as an image")
    if conversion.get("crop"):
        x, y, w, h = conversion["crop"]
        if x + w > image.shape[1] or y + h > image.shape[0]:
            raise ValueError(f"{where}: crop {conversion['crop']} reaches outside the {image.shape[1]} x "
                             f"{image.shape[0]} image")
        image = image[y:y + h, x:x + w]
    if conversion.get("resize"):
        image = cv2.resize(image, tuple(conversion["resize"]), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(image), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError(f"{where}: OpenCV could not encode the converted image as JPEG")
    return buf.tobytes()


# -- the destination -----------------------------------------------------------------------------------------------
def check_destination(out: Path, repo: Path = REPO) -> Path:
    """OUT resolved; refused inside the repository (its images must never be committed) or when it is a file or
    a non-empty folder (nothing is overwritten)."""
    out = Path(out).expanduser().resolve()
    repo = Path(repo).resolve()
    if out == repo or repo in out.parents:
        raise ValueError(f"destination {out} lies inside the repository {repo}: the dev set's images must stay out "
                         "of it; give a folder outside, e.g. ~/data/geoloc_devset")
    if out.exists() and not out.is_dir():
        raise ValueError(f"destination {out} is a file; give a new or empty folder")
    if out.is_dir() and any(out.iterdir()):
        raise ValueError(f"destination {out} is a non-empty folder; nothing is overwritten: give a new or empty "
                         "folder, or remove this one first")
    return out


# -- layouts -------------------------------------------------------------------------------------------------------
def write(path: Path, data: bytes) -> None:
    """Written in place: the whole set is built in a temporary folder and renamed at the end (assemble)."""
    write_bytes(path, data, atomic=False)


def write_cvusa(root: Path, pairs: list[tuple[dict, bytes, dict, bytes]]) -> list[list[str]]:
    rows, table = [], []
    for k, (q, q_bytes, r, r_bytes) in enumerate(pairs, start=1):
        aerial, street = f"bingmap/19/{k:07d}.jpg", f"streetview/panos/{k:07d}.jpg"
        write(root / aerial, r_bytes)
        write(root / street, q_bytes)
        rows.append(f"{aerial},{street}\n")
        table.append([street, aerial, q["pair"]])
    write(root / "splits" / "val-19zl.csv", "".join(rows).encode())
    return table


def cvact_id(k: int) -> str:
    """22 characters, like CVACT's panoIds, so that loadmat returns them unpadded."""
    return f"devset{k:016d}"


def write_cvact(root: Path, pairs: list[tuple[dict, bytes, dict, bytes]]) -> list[list[str]]:
    import numpy as np

    table, ids = [], []
    for k, (q, q_bytes, r, r_bytes) in enumerate(pairs, start=1):
        ids.append(cvact_id(k))
        street = f"ANU_data_small/streetview/{ids[-1]}_grdView.jpg"
        aerial = f"ANU_data_small/satview_polish/{ids[-1]}_satView_polish.jpg"
        write(root / street, q_bytes)
        write(root / aerial, r_bytes)
        table.append([street, aerial, q["pair"]])
    mat = {"panoIds": np.array(ids), "valSet": {"valInd": np.arange(1, len(ids) + 1, dtype=np.int64).reshape(-1, 1)}}
    write(root / "ACT_data.mat", mat_bytes(mat, "geoloc tools/devset/assemble.py"))
    return table


def write_folder(root: Path, pairs: list[tuple[dict, bytes, dict, bytes]]) -> list[list[str]]:
    table, rows = [], []
    for k, (q, q_bytes, r, r_bytes) in enumerate(pairs, start=1):
        name = f"{k:04d}.jpg"
        write(root / "queries" / name, q_bytes)
        write(root / "tiles" / name, r_bytes)
        rows.append(f"{name},{k * PLACE_SPACING_M:.1f},0.0\n")
        table.append([f"queries/{name}", f"tiles/{name}", q["pair"]])
    for csv_name in ("queries.csv", "tiles.csv"):
        write(root / csv_name, ("image,east_m,north_m\n" + "".join(rows)).encode())
    return table


WRITERS = {"cvusa": write_cvusa, "cvact": write_cvact, "folder": write_folder}


def write_pairs_table(root: Path, table: list[list[str]], pairs: list[tuple[dict, bytes, dict, bytes]]) -> None:
    lines = io.StringIO()
    out = csv.writer(lines, lineterminator="\n")
    out.writerow(["query", "reference", "pair", "original_id", "repository", "commit", "query_path",
                  "reference_path", "licence", "offset_px"])
    for (query, reference, pair), (q, _, r, _) in zip(table, pairs):
        offset = q.get("offset_px")
        out.writerow([query, reference, pair, q.get("original_id", ""), q["repository"], q["commit"], q["path"],
                      r["path"], q["licence"], "" if offset is None else json.dumps(offset)])
    write(root / "pairs.csv", lines.getvalue().encode())


def chance(n: int, k: int) -> float:
    """Recall@k of a ranking drawn at random in a gallery of n references, one of them relevant."""
    return min(k, n) / n


def readme(counts: dict[str, int]) -> str:
    lines = ["geoloc dev set: real cross-view pairs from public repositories (docs/devset.md).",
             "EVALUATION ONLY: never train on it. No kind has a train split.", "",
             "Each kind is its own gallery. Chance level = the recall of a random ranking: R@K = min(K, N) / N.", ""]
    for kind, n in counts.items():
        layout = LAYOUTS[kind]
        lines += [(f"{kind}: N = {n} pairs, layout {layout}; chance R@1 = {chance(n, 1):.4f}, "
                   f"R@5 = {chance(n, 5):.4f}, R@10 = {chance(n, 10):.4f}"),
                  f"  python evaluate.py ckpt=RUN/last.pt {EVALUATE[layout].format(root=f'OUT/{kind}')}"]
    lines += ["",
              ("vigor_like is in CVACT's layout (full-sphere panoramas): no offset or GPS came with its pairs, and its "
               "tiles are not centred on the camera, so only its retrieval recall means anything."),
              ("other holds limited field-of-view street images; its positions are placeholders 1 km apart that only "
               "say which tile is whose: no metre figure on it means anything."),
              "OUT/<kind>/pairs.csv names the repository, commit, path and licence of every pair."]
    return "\n".join(lines) + "\n"


# -- assembly ------------------------------------------------------------------------------------------------------
def assemble(out: Path, source, manifest: Path = MANIFEST, repo: Path = REPO) -> dict[str, int]:
    """Build the set in OUT (checked first, written through a temporary folder beside it and renamed at the end,
    so a failed run leaves no half set); returns {kind: number of pairs}."""
    out = check_destination(out, repo)
    entries = load_manifest(manifest)
    out.parent.mkdir(parents=True, exist_ok=True)
    work = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(work, ignore_errors=True)
    counts = {}
    try:
        for kind, pairs in pairs_by_kind(entries).items():
            ready = [(q, converted(checked_bytes(source, q), q), r, converted(checked_bytes(source, r), r))
                     for q, r in pairs]
            table = WRITERS[LAYOUTS[kind]](work / kind, ready)
            write_pairs_table(work / kind, table, ready)
            counts[kind] = len(ready)
        write(work / "README.txt", readme(counts).encode())
        if out.is_dir():
            out.rmdir()  # empty, as check_destination found it
        os.replace(work, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path, help="a new or empty folder outside the repository")
    parser.add_argument("--mirror", type=Path, help="folder of <owner>+<name>/ git copies (default: download)")
    parser.add_argument("--manifest", type=Path, default=MANIFEST)
    args = parser.parse_args(argv)
    source = MirrorSource(args.mirror) if args.mirror else WebSource()
    try:
        counts = assemble(args.out, source, args.manifest)
    except (ValueError, FileNotFoundError, ConnectionError) as err:
        print(f"assemble.py: {err}", file=sys.stderr)
        return 1
    for kind, n in counts.items():
        print(f"{kind}: {n} pairs -> {Path(args.out) / kind}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
