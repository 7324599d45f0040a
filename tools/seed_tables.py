"""Mean ± std over seeds of the markdown tables several runs wrote (`table_<n>.md`, e.g. mmdip_tables' Tables I-IV).

    python tools/seed_tables.py RUN_SEED0 RUN_SEED1 RUN_SEED2 [--out DIR] [--digits 4]

Each run folder must hold the same tables with the same rows and columns (the same command, another `seed=`). A
cell that is a number in every run becomes `mean ± std` (sample std, n-1); a text cell must be equal in every run
and is kept. Prints each table and writes it to DIR/table_<n>.md when --out is given.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path


def read_table(path: Path) -> tuple[list[str], list[list[str]]]:
    """(the lines before the table, its rows as lists of cells; the header first, the separator dropped)."""
    lines = path.read_text().splitlines()
    head = [line for line in lines if not line.startswith("|")]
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines if line.startswith("|")]
    return head, [r for r in rows if not all(set(c) <= set("-: ") for c in r)]


def number(cell: str) -> float | None:
    try:
        return float(cell)
    except ValueError:
        return None


def combine(cells: list[str], digits: int, where: str) -> str:
    values = [number(c) for c in cells]
    if all(v is not None for v in values):
        std = statistics.stdev(values) if len(values) > 1 else 0.0
        return f"{statistics.fmean(values):.{digits}f} ± {std:.{digits}f}"
    if len(set(cells)) > 1:
        raise ValueError(f"{where}: the runs disagree on a text cell {cells}: are they the same command?")
    return cells[0]


def seed_table(paths: list[Path], digits: int) -> str:
    tables = [read_table(p) for p in paths]
    head, first = tables[0]
    for path, (_, rows) in zip(paths[1:], tables[1:]):
        if [len(r) for r in rows] != [len(r) for r in first] or rows[0] != first[0]:
            raise ValueError(f"{path} does not have the rows and columns of {paths[0]}")
    out = [" | ".join(first[0])]
    for i, row in enumerate(first[1:], start=1):
        out.append(" | ".join(combine([t[1][i][j] for t in tables], digits, f"{paths[0].name} row {i}")
                              for j in range(len(row))))
    title = [line for line in head if line.strip()][:1]
    lines = [*title, "", f"| {out[0]} |", "|" + "---|" * len(first[0]), *(f"| {r} |" for r in out[1:])]
    return "\n".join(lines) + f"\n\n(mean ± std over {len(paths)} runs: {', '.join(p.parent.name for p in paths)})\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path)
    p.add_argument("--digits", type=int, default=4)
    args = p.parse_args(argv)
    names = sorted({f.name for f in args.runs[0].glob("table_*.md")})
    if not names:
        print(f"{args.runs[0]} holds no table_*.md", file=sys.stderr)
        return 2
    for name in names:
        text = seed_table([run / name for run in args.runs], args.digits)
        print(text)
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / name).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
