"""``report.html``: the evaluation report as one static page that opens from disk (no server, no script).

:func:`write_page` draws what ``report.write_report`` already computed (Table 1's rows, the markdown tables of the
paired tests and the other sections, Figure 3) and adds a grid of seeds x conditions coloured by outcome (Figure 3's
colours), each cell linking to the videos ``wamplan eval`` wrote for that episode where they exist::

    videos/c{condition}_seed{seed:04d}_{success|failure}.webm        the episode
    videos/c{condition}_seed{seed:04d}_{outcome}_plan.webm           the plan beside the real outcome
    videos/pairs/seed{seed:04d}_c{a}_vs_c{b}.webm                    conditions a and b side by side on one seed

Links are relative (the page, its figure and the videos move together). Only files that exist are linked.
"""

from __future__ import annotations

import os
import re
from html import escape
from pathlib import Path
from typing import Any, Sequence
from urllib.parse import quote

from wamplan.envs.spec import TaskSpec
from wamplan.evaluation.videos import PAIR_NAME, PAIRS, VIDEOS, variant_of, video_name

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 24px auto; max-width: 1100px; color: #222; padding: 0 16px; }
h1 { font-size: 22px; } h2 { font-size: 17px; margin-top: 28px; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 8px 0; } th, td { border: 1px solid #ccc; padding: 3px 8px; }
th { background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.ci { display: inline-block; position: relative; width: 120px; height: 10px; background: #eee; margin-left: 8px;
      vertical-align: middle; } .ci span { position: absolute; top: 0; height: 10px; background: #8fbc8f; }
.ci i { position: absolute; top: -2px; width: 2px; height: 14px; background: #1b5e20; }
.grid td { text-align: center; min-width: 64px; font-size: 12px; } .grid a { color: inherit; margin: 0 2px; }
.swatch { display: inline-block; width: 12px; height: 12px; margin: 0 4px 0 12px; vertical-align: middle; }
img { max-width: min(100%, 720px); display: block; } code { background: #f3f3f3; padding: 0 3px; } .note { color: #555; }
"""


def _inline(text: str) -> str:
    """Markdown's inline code (`x`) as <code>, the rest escaped."""
    return "".join(f"<code>{escape(p)}</code>" if i % 2 else escape(p) for i, p in enumerate(text.split("`")))


def md_table(md: str) -> str:
    """A markdown table (as ``report.markdown_*`` write them: a header, a rule, rows; ``\\|`` inside a cell) as HTML."""
    lines = [ln.strip() for ln in md.strip().splitlines()]
    cells = [[c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", ln[1:-1])] for ln in lines]
    head, body = cells[0], cells[2:]
    return ("<table><tr>" + "".join(f"<th>{_inline(h)}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in row) + "</tr>" for row in body)
            + "</table>")


def _text_color(bg: str) -> str:
    r, g, b = (int(bg[i:i + 2], 16) for i in (1, 3, 5))
    return "#000" if 0.299 * r + 0.587 * g + 0.114 * b > 150 else "#fff"


def table1_html(rows: list[dict[str, Any]]) -> str:
    """Table 1 from ``report.table1``'s rows: each success rate with its 95 % Wilson interval, drawn as a bar."""
    out = ["<table><tr><th>Condition</th><th>Dynamics</th><th>Seed</th><th>Target</th><th>Episodes</th>"
           "<th>Success (95% CI)</th><th>Length mean</th><th>Length median</th></tr>"]
    for r in rows:
        lo, hi, p = (100 * r[k] for k in ("ci_low", "ci_high", "success_rate"))
        bar = (f'<span class="ci" title="95% interval {lo:.0f}–{hi:.0f}%"><span style="left:{lo:.1f}%;'
               f'width:{hi - lo:.1f}%"></span><i style="left:{p:.1f}%"></i></span>')
        length = ["—" if r[k] is None else f"{r[k]:.0f}" for k in ("mean_length", "median_length")]
        out.append(f"<tr><td class=num>{r['condition']}</td><td>{escape(r['dynamics'])}</td><td>{r['seed']}</td>"
                   f"<td>{r['target']}</td><td class=num>{r['episodes']}</td><td class=num>{p:.0f}% ({lo:.0f}–{hi:.0f})"
                   f"{bar}</td><td class=num>{length[0]}</td><td class=num>{length[1]}</td></tr>")
    return "".join(out) + "</table>"


def stages_html(rows: list[dict[str, Any]], colors: dict[str, str]) -> str:
    """Episodes per outcome and condition (Figure 3's counts), outcomes in Figure 3's colours."""
    head = "".join(f'<th><span class="swatch" style="background:{c}"></span>{escape(o.replace("_", " "))}</th>'
                   for o, c in colors.items())
    body = "".join(f"<tr><td class=num>{r['condition']}</td>" + "".join(
        f"<td class=num>{r['outcomes'].get(o, 0)}</td>" for o in colors) + "</tr>" for r in rows)
    return f"<table><tr><th>Condition</th>{head}</tr>{body}</table>"


def find_videos(dirs: Sequence[Path], out: Path) -> dict[tuple[int, int], list[tuple[str, str]]]:
    """(condition, seed) -> [(label, link relative to ``out``)] of the videos in ``dirs`` (the first directory holding a
    file wins); the episode and plan videos are matched to records by :func:`grid_html`, the pairs here."""
    found: dict[tuple[int, int], list[tuple[str, str]]] = {}
    for d in dirs:
        for path in sorted((d / VIDEOS / PAIRS).glob("seed*_c*_vs_c*.webm")):
            m = PAIR_NAME.fullmatch(path.name)
            if m:
                seed, a, b = map(int, m.groups())
                for c in (a, b):
                    found.setdefault((c, seed), []).append((f"{a} vs {b}", _link(path, out)))
    return found


def _link(path: Path, out: Path) -> str:
    return quote(os.path.relpath(path, out).replace(os.sep, "/"))


def _episode_videos(rec: dict[str, Any], dirs: Sequence[Path], out: Path) -> list[tuple[str, str]]:
    """The episode video and the plan video of a record, where a directory of ``dirs`` holds them."""
    links = []
    for label, plan in (("episode", False), ("plan", True)):
        name = video_name(rec["condition"], rec["seed"], bool(rec["success"]), variant_of(rec), plan)
        hit = next((d / VIDEOS / name for d in dirs if (d / VIDEOS / name).is_file()), None)
        if hit is not None:
            links.append((label, _link(hit, out)))
    return links


def grid_html(by: dict[int, dict[int, dict[str, Any]]], colors: dict[str, str], dirs: Sequence[Path],
              out: Path) -> str:
    """Seeds (rows) x conditions (columns) of the open-loop records ``by`` (condition -> seed -> record), each cell in
    its outcome's colour with the episode's length and links to its videos."""
    conditions = sorted(by)
    seeds = sorted({s for c in conditions for s in by[c]})
    pairs = find_videos(dirs, out)
    legend = "".join(f'<span class="swatch" style="background:{c}"></span>{escape(o.replace("_", " "))}'
                     for o, c in colors.items())
    out_rows = [f'<p class="note">Outcome:{legend}. Each cell: the episode\'s length in steps; ▶ its video, '
                "plan: the plan beside the real outcome, a vs b: the two conditions side by side.</p>",
                '<table class="grid"><tr><th>Seed \\ condition</th>' + "".join(f"<th>{c}</th>" for c in conditions)
                + "</tr>"]
    for s in seeds:
        cells = []
        for c in conditions:
            rec = by[c].get(s)
            if rec is None:
                cells.append("<td></td>")
                continue
            bg = colors.get(rec["outcome"], "#9e9e9e")
            links = " ".join(f'<a href="{href}">{"▶" if label == "episode" else escape(label)}</a>'
                             for label, href in _episode_videos(rec, dirs, out) + pairs.get((c, s), []))
            title = escape(f"seed {s}, condition {c}: {rec['outcome'].replace('_', ' ')}, {rec['length']} steps")
            cells.append(f'<td style="background:{bg};color:{_text_color(bg)}" title="{title}">{rec["length"]} '
                         f"{links}</td>")
        out_rows.append(f"<tr><th>{s}</th>{''.join(cells)}</tr>")
    return "".join(out_rows) + "</table>"


def write_page(path: Path, *, title: str, notes: list[str], rows: list[dict[str, Any]], task: TaskSpec,
               colors: dict[str, str], by: dict[int, dict[int, dict[str, Any]]], paired: tuple[str, str] | None,
               sections: list[tuple[str, str]], figure: str, dirs: Sequence[Path]) -> Path:
    """Write the page to ``path``: ``notes`` (markdown lines: settings, merged runs), Table 1 (``rows``), the outcomes
    per condition with ``figure`` (a file name beside the page), the paired tests (``paired``: heading, markdown
    table), the grid of ``by``, then ``sections`` ((heading, markdown table) pairs, in report.md's order). ``dirs``:
    where videos are looked for, the page's own directory first."""
    parts = [f"<h1>{escape(title)}</h1>", *(f'<p class="note">{_inline(n)}</p>' for n in notes if n),
             "<h2>Table 1: success rate and length of successful episodes</h2>", table1_html(rows),
             f"<h2>Where the episodes ended ({escape(task.name)}'s outcomes, earliest failure first)</h2>",
             stages_html(rows, colors), f'<img src="{quote(figure)}" alt="Figure 3: episode outcomes per condition">']
    for heading, md in [paired] if paired else []:
        parts += [f"<h2>{_inline(heading)}</h2>", md_table(md)]
    parts += ["<h2>Seeds × conditions</h2>", grid_html(by, colors, dirs, path.parent)]
    for heading, md in sections:
        parts += [f"<h2>{_inline(heading)}</h2>", md_table(md)]
    path.write_text('<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><link rel="icon" href="data:,">'
                    f"<title>{escape(title)}</title><style>{STYLE}</style></head><body>\n" + "\n".join(parts)
                    + "\n</body></html>\n", encoding="utf-8")
    return path
