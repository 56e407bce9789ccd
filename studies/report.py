"""Markdown pieces of a study report: sections with figures and tables."""
from __future__ import annotations

import math


def markdown_table(df, fmt: str = "{:.4g}") -> str:
    """A pandas DataFrame as a Markdown table (index as the first column), numbers formatted by ``fmt``."""
    def cell(v, index=False):
        if isinstance(v, float):
            if math.isnan(v):
                return "–"
            return str(int(v)) if index and v.is_integer() else fmt.format(v)
        return str(v)

    head = [str(df.index.name or "")] + [str(c) for c in df.columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([cell(idx, index=True)] + [cell(v) for v in row.values]) + " |")
    return "\n".join(lines)


def section(title: str, figures, tables: dict) -> str:
    """A report section: title, figures (PNG paths relative to the report), then captioned tables."""
    parts = [f"## {title}", ""]
    parts += [f"![{f.stem}]({f.name})" for f in figures]
    for caption, table in tables.items():
        parts += ["", f"{caption}:", "", table]
    return "\n".join(parts) + "\n"
