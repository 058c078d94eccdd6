"""The records of ``benchmarks/gpu.py``: one row per measurement, the machine, and the JSON + Markdown outputs."""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import shlex
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import torch

JSON_FILE, MD_FILE = "gpu_bench.json", "gpu_bench.md"


@dataclass
class Row:
    """One measured variant: ``seconds`` is the median per ``unit`` of work, ``flops`` that unit's FLOPs."""

    part: str
    dtype: str
    variant: str
    seconds: float | None
    unit: str
    throughput: float | None = None
    throughput_unit: str | None = None
    flops: int | None = None
    projection: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    skipped: bool = False

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def tflops(self) -> float | None:
        return self.flops / self.seconds / 1e12 if self.ok and self.flops and self.seconds else None

    def summary(self) -> str:
        if not self.ok:
            return f"ERROR {self.error}"
        rate = f", {self.tflops:.3g} TFLOP/s" if self.tflops else ""
        return f"{fmt_time(self.seconds)}/{self.unit}{rate}"


def error_row(part: str, dtype: str, variant: str, error: str, skipped: bool = False) -> Row:
    return Row(part, dtype, variant, None, "", error=error, skipped=skipped)


def machine_info(dev: torch.device) -> dict[str, Any]:
    """What the figures were measured on."""
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else (platform.processor() or platform.machine())
    try:
        transformers = metadata.version("transformers")
    except metadata.PackageNotFoundError:
        transformers = None
    return {"device": str(dev), "device_name": name, "torch": torch.__version__, "cuda": torch.version.cuda,
            "transformers": transformers, "python": platform.python_version(), "platform": platform.platform(),
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "float32_matmul_precision": torch.get_float32_matmul_precision()}


# ------------------------------------------------------------------------------------------------ formatting
def fmt_time(sec: float | None) -> str:
    if sec is None:
        return "-"
    if sec >= 1:
        return f"{sec:.2f} s"
    return f"{sec * 1e3:.3g} ms" if sec >= 1e-3 else f"{sec * 1e6:.3g} µs"


def fmt_num(x: float | None) -> str:
    if x is None:
        return "-"
    return f"{x:,.0f}" if x >= 100 else f"{x:.3g}"


def bf16_reference(report: dict[str, Any]) -> float | None:
    """The bf16 matrix rate (TFLOP/s) measured in this run, if the matmul part ran."""
    rows = report["sections"].get("matmul", {}).get("rows", [])
    return next((r.tflops for r in rows if r.dtype == "bfloat16" and r.tflops), None)


def row_record(r: Row, ref: float | None) -> dict[str, Any]:
    return dataclasses.asdict(r) | {"tflops": r.tflops, "of_bf16_matmul": r.tflops / ref if r.tflops and ref else None}


def md_row(r: Row, ref: float | None) -> str:
    dt = {"bfloat16": "bf16", "float32": "fp32"}.get(r.dtype, r.dtype)
    if not r.ok:
        return f"| {r.part} | {dt} | {r.variant} | {'skipped' if r.skipped else 'error'}: {r.error} | | | | |"
    share = f"{100 * r.tflops / ref:.1f} %" if r.tflops and ref else "-"
    rate = f"{fmt_num(r.throughput)} {r.throughput_unit}" if r.throughput else "-"
    return (f"| {r.part} | {dt} | {r.variant} | {fmt_time(r.seconds)}/{r.unit} | {rate} | {fmt_num(r.tflops)} "
            f"| {share} | {r.projection or ''} |")


def flops_note(sections: dict[str, Any]) -> str:
    parts = []
    if "flops_per_chunk" in sections.get("plan", {}):
        p = sections["plan"]
        parts.append(f"planning {p['flops_per_chunk']['cached'] / 1e12:.3g} TFLOP per chunk KV-cached, "
                     f"{p['flops_per_chunk']['naive'] / 1e12:.3g} naive ({p['planner']} {p['candidates']} x "
                     f"{p['iterations']}, {p['rollout_steps']} rollout steps, {p['params'] / 1e6:.3g} M params)")
    if "flops_per_image" in sections.get("encoder", {}):
        parts.append(f"DINOv3 {sections['encoder']['flops_per_image'] / 1e9:.3g} GFLOP per image")
    if "flops_per_window" in sections.get("train", {}):
        t = sections["train"]
        parts.append(f"training {t['flops_per_window'] / 1e12:.3g} TFLOP per window (forward + backward); "
                     f"windows per epoch = {t['windows_per_epoch_rule']}")
    return "; ".join(parts)


def markdown(report: dict[str, Any]) -> str:
    m, ref, secs = report["machine"], bf16_reference(report), report["sections"]
    lines = ["# wamplan GPU benchmark (issue 42)", "",
             f"- command: `{shlex.join(report['argv'])}`",
             f"- machine: {m['device_name']} ({m['device']}), torch {m['torch']} (CUDA {m['cuda']}), transformers "
             f"{m['transformers']}, {m['cpu_count']} CPUs, fp32 matmul precision {m['float32_matmul_precision']}",
             f"- commit {report['git_commit']}, {report['provenance']['created']}"]
    if report["settings"]["tiny"]:
        lines.append("- **--tiny: toy sizes; these figures time the code path, not the paper's models**")
    lines += ["", "| part | dtype | variant | median | throughput | TFLOP/s | of bf16 matmul | projection |",
              "|---|---|---|---|---|---|---|---|"]
    lines += [md_row(r, ref) for sec in secs.values() for r in sec["rows"]]
    note = flops_note(secs)
    lines.append("")
    if note:
        lines.append(f"FLOPs (FlopCounterMode on meta tensors: matmuls and attention, multiply-add = 2): {note}.")
    for mode, why in secs.get("plan", {}).get("modes_not_measured", {}).items():
        lines.append(f"- plan mode {mode} not measured: {why}")
    failed = {n: sec["error"] for n, sec in secs.items() if not sec["ok"]}
    lines += [f"- part {n} did not run: {e}" for n, e in failed.items()]
    return "\n".join(lines) + "\n"


def write_outputs(report: dict[str, Any], out: Path) -> None:
    """``out/gpu_bench.json`` (every field) and ``out/gpu_bench.md`` (the table)."""
    out.mkdir(parents=True, exist_ok=True)
    ref = bf16_reference(report)
    record = dict(report, bf16_matmul_tflops=ref, sections={
        n: dict(sec, rows=[row_record(r, ref) for r in sec["rows"]]) for n, sec in report["sections"].items()})
    (out / JSON_FILE).write_text(json.dumps(record, indent=2, default=str) + "\n")
    (out / MD_FILE).write_text(markdown(report))
