"""Counterfactual branches (wamplan/data/branch.py): the parent's history, the perturbed chunk, the windows."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from wamplan.data.branch import BranchSpec, collect_branched, drop_unfinished_branches, parent_seed
from wamplan.data.collect import collect
from wamplan.data.readers import WorldModelWindows
from wamplan.data.store import EpisodeStore
from wamplan.envs.config import EnvConfig
from wamplan.envs.contract import CAMERAS
from wamplan.errors import UserError
from wamplan.policies.base import make_policy
from wamplan.policies.rollout import run_episode

SPEC = BranchSpec(branches=2, chunk=16, context_steps=8, sigmas=(0.1, 0.3))


@pytest.fixture(scope="module")
def branched(small_env):
    return collect_branched(small_env, make_policy("expert"), 3, "policy:expert", 4, SPEC, max_steps=40)


def test_branches_start_in_the_parents_past_and_run_their_own_chunk(branched, small_env):
    parent, branches = branched
    assert parent.length == 40 and len(branches) == 2  # boundary 16 only: 32 + 16 > 40
    for j, b in enumerate(branches):
        assert b.seed == 3000 + j and parent_seed(b.seed) == 3 and b.source == "branch:expert"
        assert b.length == 24 and b.policy["branch_step"] == 16 and b.policy["sigma"] == SPEC.sigmas[j]
        np.testing.assert_array_equal(b.actions[:8], parent.actions[8:16])  # the shared past
        np.testing.assert_array_equal(b.proprio[:9], parent.proprio[8:17])
        noise = b.actions[8:] - parent.actions[16:32]  # the branch's own chunk
        assert 0.3 * SPEC.sigmas[j] < noise[np.abs(parent.actions[16:32]) < 0.5].std() < 2 * SPEC.sigmas[j]
        assert list(b.image_steps) == [0, 4, 8, 12, 16, 20, 24]
        for c in CAMERAS:
            k = list(parent.image_steps).index(16)
            np.testing.assert_array_equal(b.images[c][:3], parent.images[c][k - 2:k + 1])
            assert not np.array_equal(b.images[c][-1], parent.images[c][list(parent.image_steps).index(32)])
    # the branch's end state is where its actions lead from the parent's state at step 16
    expert = make_policy("expert")
    acts = iter(list(parent.actions[:16]) + list(branches[1].actions[8:]))
    expert.act = lambda obs: next(acts)
    run_episode(small_env, expert, 3, max_steps=32)
    end = small_env.privileged_state()["cube_pose"][:3], small_env.privileged_state()["tcp_pose"][:3]
    np.testing.assert_allclose(end[1], branches[1].tcp_pose[-1][:3], atol=3e-3)
    np.testing.assert_allclose(end[0], branches[1].cube_pose[-1][:3], atol=3e-3)


def test_collect_writes_branches_before_parents_and_windows_read_them(tmp_path):
    out = tmp_path / "br"
    s = collect("policy", 1, out, seed_start=3, policy="expert", max_steps=40, progress=False,
                branch=SPEC, env=EnvConfig(camera_size=64))
    assert s["collected"] == 1
    store = EpisodeStore(out)
    assert store.finished_seeds("policy:expert") == {3} and store.finished_seeds("branch:expert") == {3000, 3001}
    ds = WorldModelWindows([out], frameskip=4, history=3, horizon=2, split="all", sources=["branch:expert"])
    assert sorted(int(ds[i]["steps"][0]) for i in range(len(ds))) == [0, 0, 4, 4]  # two windows per branch
    # an interrupted parent: its branches are on disk, the parent is not -> dropped, then re-collected
    store.episode_path("policy:expert", 3).unlink()
    assert drop_unfinished_branches(store, "policy:expert") == 2 and store.finished_seeds("branch:expert") == set()
    with pytest.raises(Exception, match="--branches needs --source policy"):
        collect("expert", 1, tmp_path / "x", branch=SPEC, progress=False)


def test_branches_share_their_parents_split_and_stay_in_their_seed_space(small_env):
    from wamplan.data.readers import split_of

    for parent in range(40):
        side = split_of("policy:tinywam", parent, 0.3)
        assert all(split_of("branch:tinywam", parent * 1000 + j, 0.3) == side for j in (0, 7, 99))
    assert {split_of("policy:tinywam", p, 0.3) for p in range(40)} == {"train", "val"}
    with pytest.raises(ValueError, match="fewer --branches"):
        collect_branched(small_env, make_policy("expert"), 3, "policy:expert", 4, BranchSpec(branches=60))


def test_branch_steps_restrict_the_boundaries(small_env, tmp_path, capsys):
    spec = BranchSpec(branches=1, chunk=16, context_steps=8, sigmas=(0.1,), steps=(30, 40))
    parent, branches = collect_branched(small_env, make_policy("expert"), 5, "policy:expert", 4, spec, max_steps=56)
    assert [b.policy["branch_step"] for b in branches] == [32]  # 16 and 48 lie outside 30..40 (48 also ends late)
    with pytest.raises(ValueError, match="lo <= hi"):
        BranchSpec(steps=(40, 30))
    from wamplan.cli import main

    base = ["collect", "--source", "policy", "--policy", "expert", "--episodes", "1", "--out", str(tmp_path / "x")]
    assert main(base + ["--branch-steps", "96", "128"]) == 2
    assert "add --branches N" in capsys.readouterr().err
    assert main(base + ["--branches", "2", "--branch-steps", "128", "96"]) == 2
    assert "LO <= HI" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


@pytest.fixture(scope="module")
def three_siblings(tmp_path_factory) -> Path:
    """A store of one expert parent (56 steps) with 3 branches at boundaries 16 and 32, at 64 px."""
    out = tmp_path_factory.mktemp("branches") / "br"
    spec = BranchSpec(branches=3, chunk=16, context_steps=8, sigmas=(0.1, 0.2, 0.3))
    collect("policy", 1, out, seed_start=4, policy="expert", max_steps=56, progress=False, branch=spec,
            env=EnvConfig(camera_size=64))
    return out


def test_branch_groups_stack_the_siblings_of_each_boundary(three_siblings, tmp_path, capsys):
    """BranchGroups: one item per boundary, its siblings' windows stacked; they share the context (frames up to
    the boundary and the actions before it) and differ in the chunk and the future."""
    import shutil

    from wamplan.data.readers import BranchGroups

    out = tmp_path / "br"
    shutil.copytree(three_siblings, out)  # this test deletes the branches at its end
    groups = BranchGroups([out], frameskip=4, history=3, horizon=4, split="all")
    assert groups.group == 3 and len(groups) == 2  # boundaries 16 and 32 (48 + 16 > 56)
    for i in range(len(groups)):
        item = groups[i]
        assert item["images"].shape[:2] == (3, 7) and item["a"].shape == (3, 7, 20) and item["q"].shape == (3, 7, 10)
        for j in (1, 2):
            assert torch.equal(item["images"][j, :3], item["images"][0, :3])  # the shared past, boundary included
            assert torch.equal(item["a"][j, :2], item["a"][0, :2]) and torch.equal(item["q"][j, :3], item["q"][0, :3])
            assert not torch.equal(item["a"][j, 2:6], item["a"][0, 2:6])  # each its own chunk
            assert not torch.equal(item["images"][j, -1], item["images"][0, -1])
        assert item["steps"][0].tolist() == [0, 4, 8, 12, 16, 20, 24]
    assert BranchGroups([out], frameskip=4, history=3, horizon=4, group=4, split="all").items == []
    # a model with 4 context frames needs 12 steps of shared past: these branches kept 8, so none qualify
    assert BranchGroups([out], frameskip=4, history=4, horizon=4, split="all").items == []
    # `wm train --sibling-weight` trains on those groups and logs the sibling error; without branches it says so
    from wamplan.cli import main

    run = tmp_path / "wm"
    assert main(["wm", "train", "--data", str(out), "--out", str(run), "--max-steps", "2", "--batch-size", "4",
                 "--sibling-weight", "1", "--sibling-groups", "2", "--log-every-steps", "1"]) == 0
    logged = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert any("train/sib_mse_h4" in m for m in logged)
    # in bfloat16 autocast too: the groups' float16 features are read and stacked outside it
    assert main(["wm", "train", "--data", str(out), "--out", str(tmp_path / "wm_bf16"), "--max-steps", "1",
                 "--batch-size", "4", "--sibling-weight", "1", "--sibling-groups", "2", "--precision", "bfloat16"]) == 0
    # `wm eval` scores the same groups: the share of the siblings' differences the model misses
    assert main(["wm", "eval", "--ckpt", str(run / "checkpoint"), "--data", str(out), "--split", "all",
                 "--json", str(tmp_path / "eval.json")]) == 0
    scored = json.loads((tmp_path / "eval.json").read_text())
    assert scored["sibling_groups"] == 2 and 0 < scored["sib_rel_h4"] < 10 and scored["sib_mse_h4"] > 0
    # the gain is the slope of predicted on true sibling differences, so (Cauchy-Schwarz) sib_rel >= (1 - gain)^2
    assert scored["sib_rel_h4"] >= (1 - scored["sib_gain_h4"]) ** 2 - 1e-6
    store = EpisodeStore(out)
    for s in store.finished_seeds("branch:expert"):
        store.episode_path("branch:expert", s).unlink()
    assert main(["wm", "train", "--data", str(out), "--out", str(tmp_path / "wm2"), "--max-steps", "1",
                 "--sibling-weight", "1"]) == 2
    assert "groups of counterfactual branches" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore:TinyWAM was trained on 224-px renders")  # a 64-px store keeps the test short
def test_each_group_gets_the_wams_predicted_views_at_its_boundary_as_its_target(three_siblings):
    """wam.targets.group_targets: the WAM's predicted views at each group's boundary, encoded (the lab's ranking
    probes score the siblings against them); BranchGroups.with_targets hands each item its group's."""
    from wamplan.data.readers import BranchGroups
    from wamplan.encoders import make_encoder
    from wamplan.wam.base import load_wam
    from wamplan.wam.targets import group_targets

    wam = load_wam("checkpoints/mini/tinywam", device="cpu")
    groups = BranchGroups([three_siblings], frameskip=4, history=3, horizon=4, split="all")
    targets = group_targets(wam, groups, make_encoder("patch-pixels", input_size=64))
    assert targets.shape == (2, 3, 16, 128) and not torch.equal(targets[0], targets[1])  # one per boundary
    item = groups.with_targets(targets)[1]
    assert torch.equal(item["target"], targets[1]) and item["a"].shape == (3, 7, 20)


def test_planned_collection_follows_the_planners_chunks_and_branches_them(tmp_path):
    """``collect --plan-with WM``: the parent is condition 7's planned policy (the first chunk open loop, the
    next one planned, so it leaves the open-loop WAM's actions), stored under its own source, and its branches
    perturb the chunk the planner executed."""
    wam, wm = "checkpoints/mini/tinywam", "checkpoints/mini/wm_augmented"
    from wamplan.evaluation.build import load_policy

    kw = dict(seed_start=7, policy=wam, max_steps=32, progress=False, loader=load_policy)
    collect("policy", 1, tmp_path / "open", **kw)
    s = collect("policy", 1, tmp_path / "planned", branch=BranchSpec(branches=1, sigmas=(0.1,)), plan_with=wm, **kw)
    tag = "policy:tinywam+plan:wm_augmented"
    assert s["source"] == tag
    store = EpisodeStore(tmp_path / "planned")
    assert store.finished_seeds(tag) == {7} and store.finished_seeds("branch:tinywam+plan:wm_augmented") == {7000}
    planned = store.load(store.episode_path(tag, 7))
    opened = EpisodeStore(tmp_path / "open").load(EpisodeStore(tmp_path / "open").episode_path("policy:tinywam", 7))
    assert planned.policy["name"] == "planned" and planned.length == opened.length == 32
    assert planned.policy["world_models"] == [str(Path(wm).resolve())]  # which model planned it
    np.testing.assert_allclose(planned.actions[:16], opened.actions[:16], atol=1e-6)  # the first chunk: open loop
    assert np.abs(planned.actions[16:] - opened.actions[16:]).max() > 1e-3  # the planned chunk
    branch = store.load(store.episode_path("branch:tinywam+plan:wm_augmented", 7000))
    assert branch.policy["branch_step"] == 16
    assert 0.03 < (branch.actions[8:] - planned.actions[16:32]).std() < 0.2  # σ 0.1 around the planned chunk
    again = collect("policy", 1, tmp_path / "planned", branch=BranchSpec(branches=1, sigmas=(0.1,)), plan_with=wm, **kw)
    assert again["collected"] == 0 and again["skipped"] == 1  # resumes: nothing collected twice
    with pytest.raises(UserError, match="--plan-with needs --source policy"):
        collect("expert", 1, tmp_path / "x", plan_with=wm, progress=False)
    for bad in (str(tmp_path / "no_model"), wm + ","):
        with pytest.raises(UserError, match="does not exist"):
            collect("policy", 1, tmp_path / "y", policy=wam, plan_with=bad, progress=False, loader=load_policy)
    with pytest.raises(UserError, match="loader=wamplan.evaluation.build.load_policy"):
        collect("policy", 1, tmp_path / "z", policy=wam, plan_with=wm, progress=False)


def test_a_store_refuses_a_source_whose_file_names_another_source_wrote(expert_store, tmp_path):
    """File names keep only [A-Za-z0-9_.-] of a source, so two sources can share them; resuming one onto the
    other's files would skip its seeds and mix the data. The store names both instead."""
    import shutil

    store = EpisodeStore(shutil.copytree(expert_store, tmp_path / "s"))
    store.check_source("expert")  # its own files: fine
    store.check_source("policy:nothing_here")  # no files under that name: fine
    src = store.episode_paths()[0]
    src.rename(src.with_name("policy_a_b-s0000000.h5"))  # an episode whose source attribute says "expert"
    with pytest.raises(UserError, match="holds episodes of source 'expert' under the file names of 'policy:a\\+b'"):
        store.check_source("policy:a+b")
    with pytest.raises(UserError, match="holds episodes of source 'expert'"):
        store.check_source("policy:a_b")
