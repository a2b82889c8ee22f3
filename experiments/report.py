"""The report of experiment results: one Markdown file and one HTML page in a folder.

    from experiments.report import ReportEntry, write_report
    md, html = write_report([ReportEntry(result, Path("out/experiments/feeding"))], Path("out/experiments"))

For each :class:`~experiments.result.ExperimentResult`: title, description, seed and run time,
the headline figures, the verdicts (pass/fail with target and measured), every table (units in
the headers, numbers with each column's ``digits``, None as "n/a"), the figures with their
captions, the recordings and the configuration. The HTML page is self-contained in its folder:
inline CSS, no script, no external resource; PNGs are linked by relative paths. A figure that
lies outside the report's folder is copied into ``<out>/figures/<experiment>/``. All text is
escaped (HTML) or has its table-breaking characters escaped (Markdown).
"""

from __future__ import annotations

import html
import json
import math
import os
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.result import RESULT_FILE, Column, ExperimentResult, Table

__all__ = [
    "REPORT_HTML",
    "REPORT_MD",
    "ReportEntry",
    "find_results",
    "format_value",
    "header",
    "render_html",
    "render_markdown",
    "write_report",
]

REPORT_MD = "report.md"
REPORT_HTML = "report.html"
NA = "n/a"


@dataclass(frozen=True)
class ReportEntry:
    """A result and the folder its files (figures, recordings) are in."""

    result: ExperimentResult
    folder: Path


def find_results(path: Path) -> list[Path]:
    """The result folders under ``path``: ``path`` itself when it holds ``result.json``, else every
    folder below it that does, in the registry's order then by name. ValueError if none."""
    if (path / RESULT_FILE).is_file():
        return [path]
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: no such folder")
    found = sorted({p.parent for p in path.rglob(RESULT_FILE)})
    if not found:
        raise ValueError(f"{path}: no {RESULT_FILE} in it or in a folder below it")
    from experiments.registry import EXPERIMENT_MODULES

    order = {name: i for i, name in enumerate(EXPERIMENT_MODULES)}
    return sorted(found, key=lambda p: (order.get(p.name, len(order)), str(p)))


# ---------------------------------------------------------------------------------------- values
def format_value(value: Any, digits: int | None = None) -> str:
    """A cell as text: None or a non-finite float → ``n/a`` (``inf``/``-inf`` stay), a bool →
    yes/no, an int as is, a float with ``digits`` after the point (None: 4 significant digits),
    a list element by element."""
    if value is None:
        return NA
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return NA
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        if digits is None:
            return f"{value:.4g}"
        return f"{value:.{max(0, int(digits))}f}"
    if isinstance(value, list | tuple):
        return ", ".join(format_value(v, digits) for v in value)
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True)
    return str(value)


def header(col: Column) -> str:
    """A column's header: its label and, when it has one, its unit in brackets."""
    return f"{col.label} [{col.unit}]" if col.unit else col.label


def _numeric(table: Table, col: Column) -> bool:
    vals = [r.get(col.key) for r in table.rows]
    present = [v for v in vals if v is not None]
    return bool(present) and all(isinstance(v, int | float) and not isinstance(v, bool) for v in present)


def _verdict_counts(res: ExperimentResult) -> tuple[int, int]:
    ok = sum(1 for v in res.verdicts.values() if v.get("ok"))
    return ok, len(res.verdicts) - ok


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "result"


# ---------------------------------------------------------------------------------------- files
def _figure_links(entries: Sequence[ReportEntry], out_dir: Path) -> list[list[str | None]]:
    """Per entry and figure, the path relative to ``out_dir`` (copying a figure from outside the
    folder into ``figures/<name>/``), or None when the file does not exist."""
    out_abs = out_dir.resolve()
    links: list[list[str | None]] = []
    for entry in entries:
        row: list[str | None] = []
        for fig in entry.result.figures:
            src = (entry.folder / fig.file).resolve()
            if not src.is_file():
                row.append(None)
                continue
            if src.is_relative_to(out_abs):
                row.append(src.relative_to(out_abs).as_posix())
                continue
            dest = out_abs / "figures" / _slug(entry.result.name) / Path(fig.file).name
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dest)
            row.append(dest.relative_to(out_abs).as_posix())
        links.append(row)
    return links


def _recording_link(entry: ReportEntry, rec: str, out_dir: Path) -> tuple[str, bool]:
    """``(path text, inside)``: the recording relative to the report when it lies in its folder."""
    src = (entry.folder / rec).resolve()
    out_abs = out_dir.resolve()
    if src.is_relative_to(out_abs):
        return src.relative_to(out_abs).as_posix(), True
    return os.path.relpath(src, out_abs), False


# ---------------------------------------------------------------------------------------- Markdown
def _md_cell(text: str) -> str:
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("\r", " ").replace("\n", " ")


def _md_table(head: list[str], rows: list[list[str]], right: list[bool]) -> list[str]:
    out = ["| " + " | ".join(_md_cell(h) for h in head) + " |",
           "|" + "|".join("---:" if r else "---" for r in right) + "|"]
    out += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in rows]
    return out


def render_markdown(
    entries: Sequence[ReportEntry], links: list[list[str | None]], out_dir: Path, title: str
) -> str:
    """The Markdown report (``links``: from :func:`_figure_links`)."""
    lines = [f"# {title}", ""]
    if len(entries) > 1:
        for e in entries:
            ok, bad = _verdict_counts(e.result)
            lines.append(f"- [{e.result.title}](#{_slug(e.result.name)}): {ok} of {ok + bad} verdicts pass")
        lines.append("")
    for e, fig_links in zip(entries, links, strict=True):
        res = e.result
        lines += [f'<a id="{_slug(res.name)}"></a>', "", f"## {res.title}", ""]
        lines.append(f"`{res.name}` · seed {res.seed} · run time {format_value(float(res.duration_s), 1)} s")
        lines.append("")
        if res.description:
            lines += [res.description.strip(), ""]
        if res.headline:
            lines += ["### Headline figures", ""]
            rows = [[h.label, format_value(h.value), h.unit, h.detail] for h in res.headline.values()]
            lines += _md_table(["figure", "value", "unit", "detail"], rows, [False, True, False, False])
            lines.append("")
        if res.verdicts:
            ok, bad = _verdict_counts(res)
            lines += ["### Verdicts", "", f"{ok} pass, {bad} fail.", ""]
            rows = [[k, "pass" if v.get("ok") else "**FAIL**", str(v.get("target", "")),
                     str(v.get("measured", ""))] for k, v in res.verdicts.items()]
            lines += _md_table(["check", "result", "target", "measured"], rows, [False] * 4)
            lines.append("")
        for tab in res.tables:
            lines += [f"### {tab.title}", ""]
            if tab.note:
                lines += [tab.note.strip(), ""]
            if not tab.rows:
                lines += ["(no rows)", ""]
                continue
            head = [header(c) for c in tab.columns]
            rows = [[format_value(r.get(c.key), c.digits) for c in tab.columns] for r in tab.rows]
            lines += _md_table(head, rows, [_numeric(tab, c) for c in tab.columns])
            lines.append("")
        if res.figures:
            lines += ["### Figures", ""]
            for fig, link in zip(res.figures, fig_links, strict=True):
                if link is None:
                    lines += [f"*{fig.caption}* — figure file `{fig.file}` is missing.", ""]
                else:
                    alt = fig.caption.replace("]", ")").replace("[", "(").replace("\n", " ")
                    lines += [f"![{alt}]({link})", "", f"*{fig.caption.strip()}*", ""]
        if res.recordings:
            lines += ["### Recordings", ""]
            for rec in res.recordings:
                path, inside = _recording_link(e, rec, out_dir)
                lines.append(f"- [{rec}]({path})" if inside else f"- `{path}`")
            lines.append("")
        if res.config:
            lines += ["### Configuration", "", "```json",
                      json.dumps(res.config, indent=2, sort_keys=True, default=str), "```", ""]
    return "\n".join(lines).rstrip() + "\n"


# ---------------------------------------------------------------------------------------- HTML
_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2em auto; max-width: 72em;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { border-bottom: 2px solid #ccc; padding-bottom: .2em; }
h2 { border-bottom: 1px solid #ddd; margin-top: 2.2em; }
h3 { margin-top: 1.5em; }
table { border-collapse: collapse; margin: .6em 0 1.2em; font-size: .92em; }
th, td { border: 1px solid #ccc; padding: .25em .6em; vertical-align: top; }
th { background: #f2f2f2; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.pass td.result { color: #176b1b; font-weight: 600; }
tr.fail td.result { color: #b00020; font-weight: 700; }
tr.fail { background: #fff0f0; }
.meta { color: #666; font-size: .9em; }
figure { margin: 1em 0 1.6em; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { color: #444; font-size: .92em; margin-top: .3em; }
pre { background: #f7f7f7; padding: .8em; overflow-x: auto; font-size: .85em; }
code { background: #f3f3f3; padding: 0 .2em; }
.missing { color: #b00020; }
"""


def _h(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _inline(text: str) -> str:
    """Escaped text with ``code`` spans as <code>."""
    parts = str(text).split("`")
    return "".join(_h(p) if i % 2 == 0 else f"<code>{_h(p)}</code>" for i, p in enumerate(parts))


def _paragraphs(text: str) -> str:
    paras = [p.strip() for p in re.split(r"\n\s*\n", text.strip()) if p.strip()]
    return "\n".join(f"<p>{_inline(p)}</p>" for p in paras)


def _html_table(head: list[str], rows: list[list[str]], right: list[bool],
                row_classes: list[str] | None = None, cell_classes: list[str] | None = None) -> str:
    out = ["<table>", "<thead><tr>" + "".join(f"<th>{_h(h)}</th>" for h in head) + "</tr></thead>", "<tbody>"]
    for i, row in enumerate(rows):
        cls = f' class="{row_classes[i]}"' if row_classes else ""
        cells = []
        for j, c in enumerate(row):
            names = ["num"] if right[j] else []
            if cell_classes and cell_classes[j]:
                names.append(cell_classes[j])
            attr = f' class="{" ".join(names)}"' if names else ""
            cells.append(f"<td{attr}>{_h(c)}</td>")
        out.append(f"<tr{cls}>" + "".join(cells) + "</tr>")
    out += ["</tbody>", "</table>"]
    return "\n".join(out)


def render_html(
    entries: Sequence[ReportEntry], links: list[list[str | None]], out_dir: Path, title: str
) -> str:
    """The HTML report (``links``: from :func:`_figure_links`)."""
    body = [f"<h1>{_h(title)}</h1>"]
    if len(entries) > 1:
        body.append("<ul>")
        for e in entries:
            ok, bad = _verdict_counts(e.result)
            body.append(f'<li><a href="#{_slug(e.result.name)}">{_h(e.result.title)}</a>: '
                        f"{ok} of {ok + bad} verdicts pass</li>")
        body.append("</ul>")
    for e, fig_links in zip(entries, links, strict=True):
        res = e.result
        body.append(f'<section id="{_slug(res.name)}">')
        body.append(f"<h2>{_h(res.title)}</h2>")
        body.append(f'<p class="meta"><code>{_h(res.name)}</code> · seed {_h(res.seed)} · run time '
                    f"{_h(format_value(float(res.duration_s), 1))} s</p>")
        if res.description:
            body.append(_paragraphs(res.description))
        if res.headline:
            body.append("<h3>Headline figures</h3>")
            rows = [[h.label, format_value(h.value), h.unit, h.detail] for h in res.headline.values()]
            body.append(_html_table(["figure", "value", "unit", "detail"], rows, [False, True, False, False]))
        if res.verdicts:
            ok, bad = _verdict_counts(res)
            body.append(f"<h3>Verdicts</h3>\n<p>{ok} pass, {bad} fail.</p>")
            items = list(res.verdicts.items())
            rows = [[k, "pass" if v.get("ok") else "FAIL", str(v.get("target", "")),
                     str(v.get("measured", ""))] for k, v in items]
            body.append(_html_table(
                ["check", "result", "target", "measured"], rows, [False] * 4,
                row_classes=["pass" if v.get("ok") else "fail" for _k, v in items],
                cell_classes=["", "result", "", ""],
            ))
        for tab in res.tables:
            body.append(f"<h3>{_h(tab.title)}</h3>")
            if tab.note:
                body.append(_paragraphs(tab.note))
            if not tab.rows:
                body.append("<p>(no rows)</p>")
                continue
            head = [header(c) for c in tab.columns]
            rows = [[format_value(r.get(c.key), c.digits) for c in tab.columns] for r in tab.rows]
            body.append(_html_table(head, rows, [_numeric(tab, c) for c in tab.columns]))
        if res.figures:
            body.append("<h3>Figures</h3>")
            for fig, link in zip(res.figures, fig_links, strict=True):
                if link is None:
                    body.append(f'<p class="missing">{_inline(fig.caption)} — figure file '
                                f"<code>{_h(fig.file)}</code> is missing.</p>")
                else:
                    body.append(f'<figure><img src="{_h(link)}" alt="{_h(fig.caption)}">'
                                f"<figcaption>{_inline(fig.caption)}</figcaption></figure>")
        if res.recordings:
            body.append("<h3>Recordings</h3>\n<ul>")
            for rec in res.recordings:
                path, inside = _recording_link(e, rec, out_dir)
                body.append(f'<li><a href="{_h(path)}">{_h(rec)}</a></li>' if inside
                            else f"<li><code>{_h(path)}</code></li>")
            body.append("</ul>")
        if res.config:
            body.append("<h3>Configuration</h3>")
            body.append(f"<pre>{_h(json.dumps(res.config, indent=2, sort_keys=True, default=str))}</pre>")
        body.append("</section>")
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
        f"<title>{_h(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
        + "\n".join(body)
        + "\n</body>\n</html>\n"
    )


def write_report(
    entries: Sequence[ReportEntry], out_dir: Path, title: str | None = None
) -> tuple[Path, Path]:
    """Write ``out_dir/report.md`` and ``out_dir/report.html`` for ``entries``; returns both paths."""
    if not entries:
        raise ValueError("no result to report")
    out_dir.mkdir(parents=True, exist_ok=True)
    if title is None:
        title = entries[0].result.title if len(entries) == 1 else "Experiments"
    links = _figure_links(entries, out_dir)
    md = out_dir / REPORT_MD
    md.write_text(render_markdown(entries, links, out_dir, title), encoding="utf-8")
    page = out_dir / REPORT_HTML
    page.write_text(render_html(entries, links, out_dir, title), encoding="utf-8")
    return md, page
