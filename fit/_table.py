"""Formatting helpers shared by the fit scripts (no maths)."""

from __future__ import annotations


def result_rows(result, truth: dict | None = None) -> list[list[str]]:
    """Rows (parameter, true, recovered, standard error, tile-robust standard error, relative
    error, error / the larger SE) for a single FitResult."""
    rows = []
    for name in ("focus_distance", "aperture_radius"):
        value = float(getattr(result, name))
        se = float(getattr(result, name + "_se"))
        se_tiles = float(getattr(result, name + "_se_tiles"))
        true = None if not truth or truth.get(name) is None else float(truth[name])
        rel = "" if true is None else f"{(value - true) / true:+.2e}"
        big = max(se, se_tiles)
        z = "" if true is None or big == 0 else f"{(value - true) / big:+.2f}"
        rows.append([name, "" if true is None else f"{true:.6g}", f"{value:.6g}", f"{se:.3g}",
                     f"{se_tiles:.3g}", rel, z])
    return rows


def format_table(rows: list[list], header=("parameter", "true", "recovered", "std err",
                                           "std err (tiles)", "rel err", "err/SE")) -> str:
    """A Markdown table with aligned columns.

    Cells may be any value (formatted with `str`; None is an empty cell); a `|` inside a cell is
    escaped so it cannot split the row (fit messages quote |CoC|).

    Raises:
        ValueError: a row whose length differs from the header's.
    """
    header = [str(h) for h in header]
    for i, r in enumerate(rows):
        if len(r) != len(header):
            raise ValueError(f"rows[{i}]: expected {len(header)} cells to match the header, got "
                             f"{len(r)}")

    def cell(c) -> str:
        return "" if c is None else str(c).replace("|", "\\|")

    table = [[cell(c) for c in header]] + [[cell(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in table]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)
