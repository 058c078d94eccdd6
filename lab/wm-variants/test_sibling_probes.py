"""The sibling-group probes: wm_action_response.py and wm_error_persistence.py on a tiny branched store."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from wamplan.data.branch import BranchSpec
from wamplan.data.collect import collect
from wamplan.data.features import feature_key
from wamplan.envs.config import EnvConfig
from wamplan.worldmodel.stores import encode_stores

from wamplan.worldmodel.load import load_world_model


@pytest.fixture(scope="module")
def three_siblings(tmp_path_factory) -> Path:
    """A store of one expert parent (56 steps) with 3 branches at boundaries 16 and 32, at 64 px."""
    out = tmp_path_factory.mktemp("branches") / "br"
    spec = BranchSpec(branches=3, chunk=16, context_steps=8, sigmas=(0.1, 0.2, 0.3))
    collect("policy", 1, out, seed_start=4, policy="expert", max_steps=56, progress=False, branch=spec,
            env=EnvConfig(camera_size=64))
    return out


def test_the_action_response_script_scores_sibling_and_drastic_changes(three_siblings, repo_script, capsys):
    """wm_action_response.py: per model, the predicted and true spread of the siblings' outcomes and the
    prediction's change under a zeroed or negated chunk; a model given without a label is one line."""
    from wamplan.data.readers import BranchGroups

    mod = repo_script("lab/wm-variants/wm_action_response.py")
    model, enc = load_world_model("checkpoints/mini/wm_augmented")
    encode_stores([three_siblings], enc, progress=False)
    groups = BranchGroups([three_siblings], 4, 3, 4, split="all", features=feature_key(enc.config_dict()))
    r = mod.action_response(model.eval(), groups, 4)
    assert r["groups"] == 2 and r["true_spread"] > 0 and r["pred_spread"] > 0
    assert r["zeroed"] > 0 and r["negated"] > 0 and r["chunk_abs"] > r["sibling_abs"] > 0
    sys.argv = ["wm_action_response.py", str(three_siblings), "checkpoints/mini/wm_augmented", "--split", "all"]
    with pytest.raises(SystemExit) as e:
        mod.main.__globals__["run_script"](mod.main, "wm_action_response")
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == ("wm_action_response: error: 'checkpoints/mini/wm_augmented': give each "
                                               "model as LABEL=CHECKPOINT, e.g. shipped=checkpoints/mini/wm_augmented")
    sys.argv = ["wm_action_response.py", str(three_siblings), "shipped=checkpoints/mini/wm_augmented", "--split", "all"]
    mod.main()
    out = capsys.readouterr().out
    assert out.startswith("shipped: 2 groups; pred_spread ") and "predicted share of the siblings' spread" in out


def test_the_error_persistence_script_pairs_windows_a_chunk_apart(three_siblings, repo_script, capsys):
    """wm_error_persistence.py: windows of one episode a chunk apart are paired (the later one's context ends where
    the earlier one's prediction does), and what is left after subtracting L times the earlier error is one
    quadratic in L through 1 at L = 0; a store without such pairs is refused in one line."""
    from wamplan.data.readers import WorldModelWindows

    mod = repo_script("lab/wm-variants/wm_error_persistence.py")
    model, enc = load_world_model("checkpoints/mini/wm_augmented")
    encode_stores([three_siblings], enc, progress=False)
    windows = WorldModelWindows([three_siblings], 4, 3, 4, split="all", features=feature_key(enc.config_dict()))
    pairs = mod.chunk_pairs(windows, 4)
    assert pairs and all(windows.items[i][0] == windows.items[j][0] for i, j in pairs)
    for i, j in pairs:  # the later window's context ends (its 3rd frame) where the earlier one's last frame is
        assert int(windows[j]["steps"][2]) == int(windows[i]["steps"][-1]) == int(windows[i]["steps"][0]) + 24
    r = mod.error_persistence(model.eval(), windows, 4)
    assert r["pairs"] == len(pairs) and -1 <= r["cosine"] <= 1 and r["error_share"] > 0
    b_plus_a, half = r["left_1"] - 1, r["left_0.5"] - 1  # left(L) = 1 + bL + aL²
    a = 2 * (b_plus_a - 2 * half)
    b = b_plus_a - a
    assert r["left_0.25"] == pytest.approx(1 + 0.25 * b + 0.0625 * a, rel=1e-4)
    sys.argv = ["wm_error_persistence.py", str(three_siblings), "shipped=checkpoints/mini/wm_augmented", "--split", "all",
                "--horizon", "8"]
    with pytest.raises(SystemExit) as e:
        mod.main.__globals__["run_script"](mod.main, "wm_error_persistence")
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("wm_error_persistence: error: ") and "no two windows a chunk apart" in err and "\n" not in err
    sys.argv = sys.argv[:-2]
    mod.main()
    assert capsys.readouterr().out.startswith(f"shipped: {len(pairs)} pairs; left_0.25 ")
