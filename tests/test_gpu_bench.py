"""benchmarks/gpu.sh (issue 42's one prepared GPU run) runs end to end on tiny sizes, so it cannot rot between
GPU sessions; its CUDA paths are the tests marked ``gpu``. No speed is asserted anywhere: only structure,
and that every figure is a finite positive number."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PARTS = {"matmul", "encoder", "train", "plan"}
QUICK = ("--tiny", "--compile-backend", "aot_eager")  # aot_eager: dynamo's tracing without inductor's minute of codegen


def run_bench(out: Path, *args: str) -> tuple[int, dict, str, str]:
    """Run benchmarks/gpu.sh into ``out``: (exit code, the JSON, the Markdown, the output's tail)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHON=sys.executable)
    proc = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu.sh"), "--out", str(out), *args],
                          capture_output=True, text=True, timeout=300, env=env)
    tail = (proc.stdout + proc.stderr)[-3000:]
    assert (out / "gpu_bench.json").is_file(), tail
    return proc.returncode, json.loads((out / "gpu_bench.json").read_text()), (out / "gpu_bench.md").read_text(), tail


def run_in_process(out: Path, *args: str, monkeypatch) -> tuple[int, dict, str]:
    """``benchmarks/gpu.py``'s main in this process (no interpreter start-up): (exit code, JSON, Markdown)."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import gpu

    rc = gpu.main(["--out", str(out), *args])
    return rc, json.loads((out / "gpu_bench.json").read_text()), (out / "gpu_bench.md").read_text()


def rows_of(report: dict) -> list[dict]:
    return [r for sec in report["sections"].values() for r in sec["rows"]]


def assert_measured(row: dict) -> None:
    assert row["error"] is None, row
    for key in ("seconds", "throughput", "tflops", "of_bf16_matmul"):
        if key == "throughput" and row["part"] == "matmul":
            continue
        assert isinstance(row[key], float) and math.isfinite(row[key]) and row[key] > 0, (key, row)


def table_rows(md: str) -> list[list[str]]:
    lines = [x for x in md.splitlines() if x.startswith("| ") and not x.startswith("| part ")]
    return [[c.strip() for c in x.strip("|").split("|")] for x in lines]


@pytest.fixture(scope="module")
def cpu_run(tmp_path_factory):
    return run_bench(tmp_path_factory.mktemp("gpu_bench"), *QUICK, "--device", "cpu")


def test_tiny_cpu_run_measures_every_part(cpu_run):
    rc, report, _, tail = cpu_run
    assert rc == 0, tail
    assert set(report["sections"]) == PARTS
    for name, sec in report["sections"].items():
        assert sec["ok"], (name, sec.get("error"))
        assert sec["rows"], name
    for row in rows_of(report):
        assert_measured(row)
    assert report["bf16_matmul_tflops"] > 0
    assert report["sections"]["encoder"]["images_to_encode"] == 236_000 * 3  # paper §4 frames x 3 views
    assert report["sections"]["train"]["windows_per_epoch"] == 236_000 - 1_600 * 24


def test_plan_rows_cover_both_dtypes_both_paths_and_compile(cpu_run):
    _, report, _, _ = cpu_run
    plan = report["sections"]["plan"]
    got = {(r["dtype"], r["extra"]["path"], r["extra"]["mode"]) for r in plan["rows"]}
    want = {(d, p, m) for d in ("bfloat16", "float32") for p, m in
            (("cached", "eager"), ("naive", "eager"), ("cached", "compile"))}
    assert got == want
    assert plan["modes_not_measured"] == {"cudagraphs": "CUDA only"}
    assert plan["flops_per_chunk"]["naive"] > plan["flops_per_chunk"]["cached"] > 0
    assert (plan["planner"], plan["candidates"], plan["iterations"]) == ("cem", 32, 4)


def test_json_carries_machine_command_and_commit(cpu_run):
    _, report, _, _ = cpu_run
    m = report["machine"]
    assert m["device"] == "cpu" and m["cpu_count"] >= 1 and m["torch"] == torch.__version__
    assert "--tiny" in report["argv"] and report["argv"][1].endswith("gpu.py")
    assert report["git_commit"]  # this checkout is a git repository
    assert report["settings"]["tiny"] is True and report["settings"]["device"] == "cpu"


def test_markdown_has_one_table_line_per_row(cpu_run):
    _, report, md, _ = cpu_run
    lines = table_rows(md)
    assert len(lines) == len(rows_of(report))
    assert all(len(cells) == 8 for cells in lines)
    assert [c[0] for c in lines] == [r["part"] for r in rows_of(report)]
    assert "--tiny" in md and "cudagraphs not measured: CUDA only" in md


def test_a_part_that_fails_is_recorded_and_the_others_still_run(tmp_path, monkeypatch):
    rc, report, md = run_in_process(tmp_path, *QUICK, "--device", "cpu", "--sections", "plan", "matmul",
                                    "--dtypes", "float32", "--planner", "no-such-planner", monkeypatch=monkeypatch)
    assert rc == 1
    plan, matmul = report["sections"]["plan"], report["sections"]["matmul"]
    assert not plan["ok"] and "no-such-planner" in plan["error"] and plan["rows"] == []
    assert matmul["ok"] and all(r["error"] is None for r in matmul["rows"])
    assert "part plan did not run" in md


def test_a_failing_variant_costs_only_its_row(tmp_path, monkeypatch):
    rc, report, md = run_in_process(tmp_path, *QUICK, "--device", "cpu", "--sections", "plan", "--dtypes", "float32",
                                    "--plan-modes", "eager", "compile", "--compile-backend", "no_such",
                                    monkeypatch=monkeypatch)
    assert rc == 1
    rows = {(r["extra"].get("path"), r["extra"].get("mode")) if r["error"] is None else r["variant"]: r
            for r in report["sections"]["plan"]["rows"]}
    assert set(rows) == {("cached", "eager"), ("naive", "eager"), "cached, compile"}
    assert "no_such" in rows["cached, compile"]["error"]
    assert rows[("cached", "eager")]["seconds"] > 0 and rows[("naive", "eager")]["seconds"] > 0
    assert sum("| error: " in line for line in md.splitlines()) == 1


def test_a_spent_budget_skips_what_is_left_and_says_so(tmp_path, monkeypatch):
    rc, report, md = run_in_process(tmp_path, "--tiny", "--device", "cpu", "--sections", "matmul", "plan",
                                    "--budget-s", "0", monkeypatch=monkeypatch)
    assert rc == 1
    for sec in report["sections"].values():
        assert not sec["ok"] and sec["error"] == "skipped: --budget-s spent" and sec["rows"] == []
    assert md.count("did not run: skipped: --budget-s spent") == 2


# ------------------------------------------------------------------------------------------------ CUDA
cuda_only = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (these are the --device cuda paths)")


@pytest.mark.gpu
@cuda_only
def test_learned_dynamics_plans_on_cuda_in_bf16():
    from wamplan.planning import make_cost, make_planner
    from wamplan.planning.dynamics import LearnedDynamics, PlanningContext
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.predictor import WorldModelPredictor

    dev, bf16 = torch.device("cuda"), torch.bfloat16
    cfg = dataclasses.replace(get_world_model_preset("paper").predictor, num_patches=4, enc_dim=32, depth=2,
                              heads=2, head_dim=16, mlp_dim=64)  # the paper's Δ 5, history 3, 3 views
    torch.manual_seed(0)
    model = WorldModelPredictor(cfg).to(dev, bf16)
    dyn = LearnedDynamics(model)
    ctx = PlanningContext(z=torch.randn(3, 3, 4, 32, dtype=bf16), q=torch.randn(3, 10, dtype=bf16),
                          a=torch.rand(2, 25, dtype=bf16) * 2 - 1)  # (Tc, V, N, D), (Tc, P), (Tc-1, Δ·A)
    dyn.prepare(ctx)
    cands = torch.rand(8, dyn.covered(16), 5, device=dev) * 2 - 1  # (B, 15, A)
    z = dyn.terminal(cands.to(bf16))  # (B, V, N, D)
    assert z.shape == (8, 3, 4, 32) and z.dtype == bf16 and z.device.type == "cuda" and z.isfinite().all()
    with torch.inference_mode():
        ref, _ = model.rollout(ctx.z[None].to(dev), ctx.q[None].to(dev), ctx.a[None].to(dev),
                               cands.to(bf16).reshape(8, 3, 25), naive=True)  # (B, S, V, N, D)
    assert torch.allclose(z.float(), ref[:, -1].float(), atol=0.1, rtol=0.05)  # KV cache = naive, to bf16
    target = torch.randn(3, 4, 32, device=dev, dtype=bf16)  # (V, N, D)
    cost = make_cost("patch")
    result = make_planner("cem", {}).plan(torch.zeros(15, 5, device=dev), lambda c: cost(dyn.terminal(c), target))
    assert result.actions.shape == (15, 5) and result.actions.isfinite().all()


@pytest.mark.gpu
@cuda_only
def test_gpu_script_runs_every_part_on_cuda(tmp_path):
    rc, report, md, tail = run_bench(tmp_path, *QUICK, "--device", "cuda")
    assert rc == 0, tail
    assert report["machine"]["device"].startswith("cuda") and report["machine"]["device_name"]
    for row in rows_of(report):
        assert_measured(row)
    assert {r["extra"]["mode"] for r in report["sections"]["plan"]["rows"]} == {"eager", "compile", "cudagraphs"}
    assert len(table_rows(md)) == len(rows_of(report))
