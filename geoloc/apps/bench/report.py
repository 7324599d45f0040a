"""The bench's table: one row per checkpoint, test set and protocol, with the published figures of the same
protocol beside it; as markdown, CSV and a JSON of everything."""

from __future__ import annotations

import csv
import io

from geoloc.apps.bench.published import matching, published, source

METRICS = ("R@1", "R@5", "R@10", "R@1%", "hit_rate", "AP")  # recall-like: shown in %
HEADING = "heading_median_deg"
METRES = "median_m"  # the top-1 tile centre's distance to the query (VIGOR's metres: they depend on the label set)
COLUMNS = ("checkpoint", "test set", "data", "protocol", "queries", "references", *METRICS,
           "heading error (°)", "median m", "labels", "published R@1 (same protocol)")


def published_beside(row: dict) -> list[dict]:
    """The published figures of `row`'s test set (its label-set variant shares them) and protocol."""
    return matching(row.get("published_as", row["test_set"]), row["fov"], row["heading"])


def cells(row: dict, footnotes: dict[str, int]) -> list[str]:
    m = row["metrics"]
    anchors = published_beside(row)
    for anchor in anchors:
        footnotes.setdefault(source(anchor), len(footnotes) + 1)
    beside = "; ".join(f"{a['method']} {a['metrics']['R@1']:.2f} [{footnotes[source(a)]}]"
                       for a in anchors if "R@1" in a["metrics"])
    return [row["checkpoint"], row["test_set"], "synthetic" if row["synthetic"] else "released", row["protocol"],
            str(m.get("num_queries", "")), str(m.get("num_references", "")),
            *(f"{100 * m[k]:.2f}" if isinstance(m.get(k), float) else "-" for k in METRICS),
            f"{m[HEADING]:.1f}" if isinstance(m.get(HEADING), float) else "-",
            f"{m[METRES]:.2f}" if isinstance(m.get(METRES), float) else "-", row.get("labels") or "-",
            beside or "-"]


def markdown(rows: list[dict], notes: list[str] = ()) -> str:
    footnotes: dict[str, int] = {}
    body = [cells(row, footnotes) for row in rows]
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell.replace("|", "/") for cell in row) + " |" for row in body]
    lines += ["", "Recall, hit rate and AP in %. Rows marked synthetic ran on geoloc's embedded synthetic worlds: the "
              "published figures stand beside them for the protocol, not for comparison."]
    lines += [f"[{n}] {text}" for text, n in footnotes.items()]
    missing = published()["not_entered"]
    if missing:
        lines.append("Not in published.yaml (no figure checked against its paper): " + "; ".join(
            f"{method} ({why})" for method, why in missing.items()))
    lines += list(notes)
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    footnotes: dict[str, int] = {}
    writer.writerows(cells(row, footnotes) for row in rows)
    return out.getvalue()


def record(rows: list[dict], settings: dict, notes: list[str], seconds: float) -> dict:
    """Everything: the settings, every row with all of evaluate.py's metrics and the published figures beside it,
    the sources."""
    return {"settings": settings, "seconds": round(seconds, 1), "notes": list(notes),
            "rows": [{**row, "published": published_beside(row)} for row in rows],
            "not_entered": published()["not_entered"]}
