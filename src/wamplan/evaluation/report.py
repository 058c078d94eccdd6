"""``wamplan report DIR``: Table 1, Figure 3, Table 2, the timing summary and the gap to the oracle from
evaluation records.

Outcomes are the task's (``TaskSpec.outcome_names``), the task being the one the directories ran (their
``eval_config.json``; a directory from before tasks were recorded ran cube-insertion, ``EnvConfig``'s default).
Readings that need the cube task's stages or measures are left out for a task without them: the insertion
columns need the stage :data:`ALIGNED`, the release table the ``align_xy_tol`` parameter and traced records."""

from __future__ import annotations

import csv
import math
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from wamplan.envs.config import EnvConfig
from wamplan.envs.spec import TaskSpec, get_task
from wamplan.evaluation.conditions import CONDITIONS
from wamplan.evaluation.records import RECORDS, no_records, read_records, read_settings
from wamplan.evaluation.report_page import write_page

REQUIRED_FIELDS = ("condition", "seed", "success", "outcome", "length")  # what every record must hold for a report
ALIGNED = "aligned"  # the stage the insertion readings (paired table, Table 2) start from, where a task has it
# Figure 3's colours: success, then the task's failures from the earliest stage on. Failures run red -> orange ->
# yellow -> light blue as they get closer to success (the cube task's four), so no failure shade can be mistaken
# for the success green; a task with more failures continues with the further shades.
SUCCESS_COLOR = "#2e7d32"
FAILURE_COLORS = ("#d32f2f", "#fb8c00", "#fdd835", "#90caf9", "#ce93d8", "#80cbc4", "#bcaaa4")


def outcome_colors(task: TaskSpec) -> dict[str, str]:
    """Figure 3's colour of each of ``task``'s outcomes."""
    failures = task.outcome_names[1:]  # the earliest first
    return {"success": SUCCESS_COLOR, **{o: FAILURE_COLORS[i % len(FAILURE_COLORS)] for i, o in enumerate(failures)}}


def default_task() -> TaskSpec:
    """The task of records that name none: the evaluation's default (``EnvConfig``'s)."""
    return get_task(EnvConfig.task)


def run_task(dirs: list[Path]) -> TaskSpec:
    """The task the evaluation directories ``dirs`` ran, from their settings (a directory whose settings name no
    task ran the default task; one without settings says nothing); one line if two ran different tasks."""
    from wamplan.errors import UserError

    found: dict[str, Path] = {}
    for d in dirs:
        if (stored := read_settings(d)) is not None:
            found.setdefault(stored.get("env.task", EnvConfig.task), d)
    if len(found) > 1:
        raise UserError("the runs evaluated different tasks (" + ", ".join(f"{t} in {d}" for t, d in found.items())
                        + "); report each task's runs apart")
    return get_task(next(iter(found), EnvConfig.task))


def _insertion_outcomes(task: TaskSpec) -> tuple[str, ...] | None:
    """The failures that reached :data:`ALIGNED` (aligned, not inserted), earliest first; None without that stage."""
    if ALIGNED not in task.stages:
        return None
    first = task.stages.index(ALIGNED)
    return tuple(o for st, o in reversed(task.outcomes) if task.stages.index(st) >= first)


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate k/n (sensible at 0% and 100% too)."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)


def sign_test(gained: int, lost: int) -> float:
    """Exact two-sided sign (McNemar) test p-value on ``gained`` vs ``lost`` discordant pairs (1.0 if none)."""
    n = gained + lost
    if n == 0:
        return 1.0
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(min(gained, lost) + 1)) / 2 ** n)


def table1(records: list[dict[str, Any]], variant: str = "open-loop") -> list[dict[str, Any]]:
    rows = []
    by_c = defaultdict(list)
    for r in records:
        if r.get("variant", "open-loop") == variant:
            by_c[r["condition"]].append(r)
    for cid in sorted(by_c):
        rs, c = by_c[cid], CONDITIONS[cid]
        k, n = sum(r["success"] for r in rs), len(rs)
        lo, hi = wilson(k, n)
        lengths = [r["length"] for r in rs if r["success"]]
        timing = defaultdict(list)
        open_loop: Counter = Counter()
        for r in rs:
            for key, v in r.get("chunk_timing_s", {}).items():
                timing[key].append(v)
            open_loop.update(r.get("open_loop_chunks", {}))
        blend = rs[0].get("oracle_blend")  # the --oracle-blend diagnostic: not the world model alone
        label = c.label if not blend else f"{c.label} {1 - blend:g} + simulator {blend:g}"
        rows.append(dict(condition=cid, dynamics=label, seed=c.seed.upper() if c.seed == "wam" else "Expert",
                         target="—" if c.target == "none" else ("WAM" if c.target == "wam" else "Expert"),
                         episodes=n, successes=k, success_rate=k / n, ci_low=lo, ci_high=hi,
                         mean_length=float(np.mean(lengths)) if lengths else None,
                         median_length=float(np.median(lengths)) if lengths else None,
                         outcomes=dict(Counter(r["outcome"] for r in rs)),
                         seeds=f"{min(r['seed'] for r in rs)}-{max(r['seed'] for r in rs)}",
                         planned_chunks=sum(r.get("planned_chunks", 0) for r in rs), open_loop_chunks=dict(open_loop),
                         **{f"mean_{k}": float(np.mean(v)) for k, v in timing.items()}))
    return rows


def _p(p: float) -> str:
    """A p-value: two decimals, or two significant digits below 0.01 (so 3e-7 does not read 0.00)."""
    return f"{p:.2f}" if p >= 0.01 else f"{p:.1e}"


def _fmt(x: float | None, digits: int = 0) -> str:
    return "—" if x is None else f"{x:.{digits}f}"


def markdown_table1(rows: list[dict[str, Any]]) -> str:
    out = ["| Condition | Dynamics | Seed | Target | Episodes | Success (95% CI) | Length mean | Length median |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['condition']} | {r['dynamics']} | {r['seed']} | {r['target']} | {r['episodes']} "
                   f"| {100 * r['success_rate']:.0f}% ({100 * r['ci_low']:.0f}–{100 * r['ci_high']:.0f}) "
                   f"| {_fmt(r['mean_length'])} | {_fmt(r['median_length'])} |")
    return "\n".join(out)


def markdown_timing(rows: list[dict[str, Any]]) -> str:
    """Per planned chunk: time per stage, and how many chunks were planned or ran open loop (and why)."""
    out = ["| Condition | WAM query (s/chunk) | target encoding (s/chunk) | search (s/chunk) | chunks planned "
           "| open loop: first / warm-up / gated / rejected |", "|---|---|---|---|---|---|"]
    for r in rows:
        ol = r.get("open_loop_chunks", {})
        reasons = ("first-chunk", "warm-up", "gated", "rejected")
        counts = " / ".join(str(ol.get(k, 0)) for k in reasons)
        older = ", ".join(f"{k} {n}" for k, n in ol.items() if k not in reasons)  # an older version's retired gates
        counts = "—" if r["condition"] == 1 else counts + (f" ({older})" if older else "")
        out.append(f"| {r['condition']} | {_fmt(r.get('mean_wam_s'), 3)} | {_fmt(r.get('mean_target_encode_s'), 3)} "
                   f"| {_fmt(r.get('mean_search_s'), 3)} | {r.get('planned_chunks', 0)} | {counts} |")
    return "\n".join(out)


def markdown_table2(records: list[dict[str, Any]], task: TaskSpec | None = None) -> str | None:
    """First chunk skipped vs planned, for conditions run both ways (appendix A, Table 2): success, the failures
    that reached no stage, and (where ``task`` has the stage :data:`ALIGNED`) the aligned ones not inserted."""
    task = task or default_task()
    variants = defaultdict(lambda: defaultdict(list))
    for r in records:
        variants[r["condition"]][r.get("variant", "open-loop")].append(r)
    both = [c for c, v in variants.items() if {"open-loop", "rest-history"} <= set(v)]
    if not both:
        return None
    cols = [(task.failure.replace("_", " ").capitalize(), (task.failure,))]
    inserted = _insertion_outcomes(task)
    if inserted is not None:
        cols.append(("Aligned, not inserted", inserted))
    out = ["| Condition | First chunk | Episodes | Success | " + " | ".join(h for h, _ in cols) + " |",
           "|---" * (4 + len(cols)) + "|"]
    for c in sorted(both):
        for v, name in (("open-loop", "skipped"), ("rest-history", "planned")):
            rs = variants[c][v]
            n = len(rs)
            pct = lambda o: 100 * sum(r["outcome"] == o for r in rs) / n  # noqa: E731
            shares = " | ".join(f"{sum(pct(o) for o in outcomes):.0f}%" for _, outcomes in cols)
            out.append(f"| {c} | {name} | {n} | {pct('success'):.0f}% | {shares} |")
    return "\n".join(out)


def open_loop_by_seed(records: list[dict[str, Any]]) -> dict[int, dict[int, dict[str, Any]]]:
    """condition -> seed -> record, of the runs without a planned first chunk (the paired tables' episodes)."""
    by: dict[int, dict[int, dict[str, Any]]] = defaultdict(dict)
    for r in records:
        if r.get("variant", "open-loop") == "open-loop":
            by[r["condition"]][r["seed"]] = r
    return by


def markdown_paired(records: list[dict[str, Any]], baseline: int = 1, task: TaskSpec | None = None) -> str | None:
    """Each condition against the baseline on the seeds both ran (paper §5: where the net gain comes from).

    Gained / lost count seeds that only one of the two solved; p is the exact two-sided sign (McNemar) test
    on those discordant seeds. "Inserted | aligned" (where ``task`` has the stage :data:`ALIGNED`) is the share
    of episodes that reached the aligned stage and went on to succeed: the insertion skill on its own.
    """
    task = task or default_task()
    by = open_loop_by_seed(records)
    if baseline not in by or len(by) < 2:
        return None
    aligned_col = ALIGNED in task.stages
    out = [f"| Condition | Seeds shared with {baseline} | Gained | Lost | p (sign test) |"
           + (f" Inserted \\| aligned (cond. {baseline} → this) |" if aligned_col else ""),
           "|---" * (6 if aligned_col else 5) + "|"]
    for c in sorted(k for k in by if k != baseline):
        seeds = sorted(set(by[c]) & set(by[baseline]))
        if not seeds:
            continue
        gained = sum(by[c][s]["success"] and not by[baseline][s]["success"] for s in seeds)
        lost = sum(by[baseline][s]["success"] and not by[c][s]["success"] for s in seeds)
        p = sign_test(gained, lost)

        def inserted(cid: int) -> str:
            aligned = [by[cid][s] for s in seeds if by[cid][s].get("reached", {}).get(ALIGNED)]
            if not aligned:
                return "—"
            return f"{100 * sum(r['success'] for r in aligned) / len(aligned):.0f}% of {len(aligned)}"

        out.append(f"| {c} | {len(seeds)} | {gained} | {lost} | {_p(p)} |"
                   + (f" {inserted(baseline)} → {inserted(c)} |" if aligned_col else ""))
    return "\n".join(out) if len(out) > 2 else None


def oracle_condition(cid: int) -> int | None:
    """The simulator-dynamics condition with ``cid``'s seed and target (5 for 6 and 7): its ceiling."""
    c = CONDITIONS[cid]
    return next((o.id for o in CONDITIONS.values()
                 if o.dynamics == "simulator" and (o.seed, o.target) == (c.seed, c.target)), None)


def gap_closed(base: np.ndarray, this: np.ndarray, ceiling: np.ndarray, resamples: int = 2000,
               rng_seed: int = 0) -> tuple[float, float, float]:
    """Share of the baseline-to-ceiling gap that ``this`` closes, (mean this - mean base) / (mean ceiling -
    mean base), on per-seed successes (n,) of the same seeds, with a 95 % percentile bootstrap over seeds
    (resamples whose gap is not positive are left out). NaN where the gap itself is not positive."""
    def ratio(idx: np.ndarray) -> np.ndarray:  # idx (R, n) -> (R,)
        gap = ceiling[idx].mean(-1) - base[idx].mean(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(gap > 0, (this[idx].mean(-1) - base[idx].mean(-1)) / gap, np.nan)

    n = len(base)
    point = float(ratio(np.arange(n)[None])[0])
    if not np.isfinite(point):
        return float("nan"), float("nan"), float("nan")
    boot = ratio(np.random.default_rng(rng_seed).integers(0, n, size=(resamples, n)))
    boot = boot[np.isfinite(boot)]
    return point, float(np.quantile(boot, 0.025)), float(np.quantile(boot, 0.975))


def markdown_gap(records: list[dict[str, Any]], baseline: int = 1) -> str | None:
    """How much of the gap from the baseline to the simulator oracle each learned world model closes, on the
    seeds all three ran (the paper's headline: condition 7 recovers 64 % of the way from condition 1 to 5)."""
    by = open_loop_by_seed(records)
    out = [f"| Condition | Oracle | Seeds shared | Successes: {baseline} / this / oracle | Gap closed (95 % CI) "
           f"| Oracle solves, this does not |", "|---|---|---|---|---|---|"]
    for c in sorted(k for k in by if CONDITIONS[k].learned):
        o = oracle_condition(c)
        seeds = sorted(set(by[c]) & set(by.get(baseline, {})) & set(by.get(o, {})))
        if not seeds:
            continue
        base, this, ceil = (np.array([by[k][s]["success"] for s in seeds], dtype=np.float64)
                            for k in (baseline, c, o))  # (n,) each
        point, lo, hi = gap_closed(base, this, ceil)
        closed = "— (no gap)" if not np.isfinite(point) else f"{100 * point:.0f}% ({100 * lo:.0f}–{100 * hi:.0f})"
        out.append(f"| {c} | {o} | {len(seeds)} | {int(base.sum())} / {int(this.sum())} / {int(ceil.sum())} "
                   f"| {closed} | {int(((ceil > 0) & (this == 0)).sum())} |")
    return "\n".join(out) if len(out) > 2 else None


def markdown_release(records: list[dict[str, Any]], task: TaskSpec | None = None) -> str | None:
    """Where each condition let the cube go (the records' privileged ``release``, the episodes whose first chunk
    ran open loop): how far from the hole's axis and how high it was on the last step it was held, how often
    that was inside the alignment tolerance (``task``'s ``align_xy_tol``), with the success of each kind. None
    when no record carries a trace (older records have none) or the task has no such tolerance."""
    task = task or default_task()
    if task.param("align_xy_tol") is None:
        return None
    by = open_loop_by_seed(records)
    tol = 1000 * task.param("align_xy_tol")
    out = [f"| Condition | Episodes traced | Let go after a grasp | Held at the end | Off the axis when let go, median "
           f"[IQR] mm | Cube bottom when let go, median mm | Let go within {tol:.0f} mm of the axis | Success: let go "
           f"within / beyond |", "|---|---|---|---|---|---|---|---|"]
    for c in sorted(by):
        traced = [r for r in by[c].values() if "release" in r]
        rel = [(r["release"]["held_mm"], r["success"]) for r in traced if r["release"]]  # ([xy, bottom] mm, success)
        if not traced:
            continue
        held = sum(bool(r.get("held_at_end")) for r in traced)
        if not rel:
            out.append(f"| {c} | {len(traced)} | 0 | {held} | — | — | — | — |")
            continue
        xy = np.array([x for (x, _), _ in rel])  # (n,) mm
        bottom = np.array([b for (_, b), _ in rel])  # (n,) mm
        near = xy <= tol  # (n,)
        ok = np.array([s for _, s in rel], bool)  # (n,)
        q1, q2, q3 = np.percentile(xy, [25, 50, 75])
        out.append(f"| {c} | {len(traced)} | {len(rel)} | {held} | {q2:.1f} [{q1:.1f}, {q3:.1f}] | {np.median(bottom):.1f} "
                   f"| {int(near.sum())} | {int(ok[near].sum())} of {int(near.sum())} / {int(ok[~near].sum())} of "
                   f"{int((~near).sum())} |")
    return "\n".join(out) if len(out) > 2 else None


def figure3(rows: list[dict[str, Any]], path: Path, task: TaskSpec | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(rows) + 3.0), 4))
    x = np.arange(len(rows))
    bottom = np.zeros(len(rows))
    colors = outcome_colors(task or default_task())
    for o, color in colors.items():
        frac = np.array([r["outcomes"].get(o, 0) / r["episodes"] for r in rows])
        ax.bar(x, 100 * frac, bottom=100 * bottom, color=color, label=o.replace("_", " "), width=0.7)
        bottom += frac
    for i, r in enumerate(rows):
        ax.text(i, 101, f"{100 * r['success_rate']:.0f}%", ha="center", va="bottom", fontsize=9)
    ax.set_xticks(x, [f"{r['condition']}\n{r['dynamics']}\n{r['seed']}/{r['target']}\nn = {r['episodes']}"
                      for r in rows], fontsize=8)
    ax.set_ylabel("episodes (%)")
    ax.set_ylim(0, 112)
    # centred on the figure, not the axes: with few conditions the axes are narrower than the title
    fig.suptitle("Episode outcomes per condition\n(n = episodes, the same seeds from the first)", fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _settings_line(out: Path, task: TaskSpec, named: bool = False) -> list[str]:
    """The planner, its search size and the settings that differ from its defaults for ``task``, from the
    directory's ``eval_config.json`` (absent: nothing); ``named``: say which directory."""
    from wamplan.config import to_dict
    from wamplan.planning import PLANNERS

    s = read_settings(out)
    if s is None:
        return []
    name = s.get("planner", "")
    size = f"{s.get('planner_config.num_candidates')} candidates × {s.get('planner_config.iterations')} iterations"
    changed = "?"
    if name in PLANNERS:
        defaults = to_dict(PLANNERS.lookup(name).config_cls().for_task(task))  # JSON-ready, as stored
        changed = ", ".join(f"{k} {s[f'planner_config.{k}']}" for k, v in defaults.items()
                            if f"planner_config.{k}" in s and s[f"planner_config.{k}"] != v) or "none"
    where = f" in `{out}`" if named else ""
    lines = [f"Planner{where}: `{name}` ({size}; changed from its defaults: {changed}; all settings in eval_config.json)"]
    if s.get("oracle_blend"):
        lines.append(f"Diagnostic: conditions 6 and 7 planned with the world model's predictions moved "
                     f"{s['oracle_blend']:g} of the way to the simulator's (`--oracle-blend`), "
                     "not the world model alone.")
    return [*lines, ""]


def run_spec(spec: str | Path) -> tuple[Path, set[int] | None]:
    """``DIR`` or ``DIR:C[,C...]`` (only those conditions of that run) -> (directory, conditions or None)."""
    from wamplan.errors import UserError

    text = str(spec)
    head, sep, tail = text.rpartition(":")
    if not sep or not tail.replace(",", "").isdigit():
        return Path(text), None
    try:
        return Path(head), {int(c) for c in tail.split(",") if c}
    except ValueError:
        raise UserError(f"{text}: expected DIR or DIR:C[,C...] (conditions as numbers, e.g. runs/a:1,7)") from None


def merged_records(specs: list[str | Path]) -> list[dict[str, Any]]:
    """The records of several evaluation directories as one run (e.g. condition 1 and condition 7 run
    apart on the same seeds), each ``DIR`` or ``DIR:C[,C...]``. A (condition, variant, seed) found in two
    directories is refused; found twice in one directory, it counts once where both records agree on
    :data:`OUTCOME_FIELDS`, and is refused (naming the seeds) where they do not."""
    from wamplan.errors import UserError

    seen: dict[tuple, Path] = {}
    records = []
    kept: dict[tuple, dict[str, Any]] = {}
    twice: dict[tuple, list[int]] = {}  # (directory, condition, variant) -> seeds recorded twice, outcomes differing
    for spec in specs:
        d, conditions = run_spec(spec)
        recs = read_records(d)
        for n, r in enumerate(recs, 1):
            lacks = [k for k in REQUIRED_FIELDS if k not in r] if isinstance(r, dict) else list(REQUIRED_FIELDS)
            if lacks:
                raise UserError(f"{d / RECORDS} record {n} lacks {', '.join(lacks)}; a report reads the records "
                                f"`wamplan eval` writes (each with {', '.join(REQUIRED_FIELDS)})")
        held = {r["condition"] for r in recs}
        missing = sorted((conditions or set()) - held)
        if missing:
            raise UserError(f"{spec}: {d} holds no records of condition(s) {missing} (it has "
                            f"{', '.join(map(str, sorted(held))) or 'none'}); name conditions it ran")
        for r in recs:
            if conditions is not None and r["condition"] not in conditions:
                continue
            key = (r["condition"], r.get("variant", "open-loop"), r["seed"])
            if key in seen and seen[key] != d:
                raise UserError(f"condition {key[0]} ({key[1]}) seed {key[2]} is in both {seen[key]} and {d}; "
                                f"keep one, e.g. {d}:<other conditions>")
            if key in kept:  # recorded twice in one directory (two runs into it at once, before eval held it)
                if _outcome(kept[key]) != _outcome(r):
                    twice.setdefault((d, *key[:2]), []).append(key[2])
                continue  # an identical duplicate counts once
            seen[key], kept[key] = d, r
            records.append(r)
    if twice:
        which = "; ".join(f"{d / RECORDS}: condition {c} ({v}) seed{'s' * (len(set(s)) > 1)} "
                          f"{', '.join(map(str, sorted(set(s))))}" for (d, c, v), s in twice.items())
        raise UserError(f"{which} recorded twice with different outcomes ({'/'.join(OUTCOME_FIELDS)}); delete one "
                        f"line of each, or evaluate those seeds again into a new --out")
    return records


OUTCOME_FIELDS = ("success", "outcome", "length")  # what the report counts of a record; the rest (times) may differ


def _outcome(rec: dict[str, Any]) -> tuple:
    """What two records of one episode must agree on to count as one (timings of two runs never agree)."""
    return tuple(rec.get(k) for k in OUTCOME_FIELDS)


def write_report(out_dir: str | Path, more: list[str | Path] = ()) -> dict[str, Path]:
    """Table 1, Figure 3, timings and the paired comparison, written into ``out_dir`` (report.md, and report.html:
    the same as one page with a grid of seeds x conditions linking to the videos); with ``more``, the
    records of those evaluation directories (``DIR`` or ``DIR:C[,C...]``) are merged with ``out_dir``'s (which
    may then be empty)."""
    from wamplan.errors import UserError, require_writable

    out = Path(out_dir)
    dirs = [out, *(run_spec(m)[0] for m in more)]
    seen: dict[Path, Path] = {}
    for d in dirs:
        first = seen.setdefault(d.resolve(), d)
        if first is not d:
            raise UserError(f"{d} is named twice; name each evaluation directory once")
    for d in dirs[1:]:
        if not (d / RECORDS).is_file():
            raise UserError(f"{d} has no evaluation records ({RECORDS}); name directories `wamplan eval` wrote")
    records = merged_records([out, *more])
    if not records:
        raise UserError(no_records(out))
    task = run_task(dirs)
    require_writable(out, "DIR", f"the report is written into DIR: make it writable, or report into a new directory "
                                 f"(`wamplan report NEW {' '.join(map(str, [out, *more]))}`)")
    out.mkdir(parents=True, exist_ok=True)
    rows = table1(records)
    paths = {"table1_md": out / "table1.md", "table1_csv": out / "table1.csv", "figure3": out / "figure3.png",
             "report": out / "report.md"}
    md1 = markdown_table1(rows)
    paths["table1_md"].write_text(md1 + "\n")
    with open(paths["table1_csv"], "w", newline="") as f:
        keys = [k for k in rows[0] if k != "outcomes"] + list(task.outcome_names)
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({**r, **{o: r["outcomes"].get(o, 0) for o in task.outcome_names}})
    figure3(rows, paths["figure3"], task)
    settings = [line for d in dirs for line in _settings_line(d, task, named=len(dirs) > 1)]
    sources = ["Runs merged: " + ", ".join(f"`{m}`" for m in ([out] if (out / RECORDS).is_file() else []) + list(more)),
               ""] if more else []
    parts = ["# Evaluation report", "", *sources, *settings,
             "## Table 1: success rate and length of successful episodes", "", md1, "", "![Figure 3](figure3.png)"]
    paired = markdown_paired(records, task=task)
    sections = [(h, t) for h, t in (("Per-chunk timing (planned chunks)", markdown_timing(rows)),
                                    ("Episode by episode against condition 1", paired),
                                    ("The gap to the simulator oracle", markdown_gap(records)),
                                    ("Where the cube was let go (privileged)", markdown_release(records, task)),
                                    ("Table 2: first chunk skipped vs planned", markdown_table2(records, task))) if t]
    for heading, text in sections:
        parts += ["", f"## {heading}", "", text]
    paths["report"].write_text("\n".join(parts) + "\n")
    # the same tables as one static page, with the grid of seeds x conditions linking to the episodes' videos
    paths["page"] = write_page(out / "report.html", title=f"Evaluation report: {out}", notes=sources + settings,
                               rows=rows, task=task, colors=outcome_colors(task), by=open_loop_by_seed(records),
                               paired=sections[1] if paired else None, figure=paths["figure3"].name, dirs=dirs,
                               sections=[x for x in sections if x[1] is not paired])
    return paths
