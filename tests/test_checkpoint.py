"""Checkpoint directories: atomic save, kind check, training-state round trip, fp16 export."""

import pytest
import torch

from wamplan.checkpoint import (CheckpointError, export_for_inference, has_training_state, load_training_state,
                                load_weights, read_config, save_checkpoint)


def _model():
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.GELU(), torch.nn.Linear(8, 2))


def test_round_trip_resume_and_export(tmp_path):
    m = _model()
    opt = torch.optim.AdamW(m.parameters(), lr=1e-2)
    m(torch.randn(3, 4)).sum().backward()
    opt.step()
    save_checkpoint(tmp_path / "ck", m, {"width": 8}, kind="toy", optimizer=opt, train_state={"step": 1})
    assert read_config(tmp_path / "ck", "toy") == {"width": 8} and has_training_state(tmp_path / "ck")
    m2 = _model()
    for p in m2.parameters():
        p.data.zero_()
    load_weights(tmp_path / "ck", m2)
    x = torch.randn(5, 4)
    torch.testing.assert_close(m2(x), m(x))
    opt2 = torch.optim.AdamW(m2.parameters(), lr=1e-2)
    assert load_training_state(tmp_path / "ck", opt2) == {"step": 1}
    torch.testing.assert_close(opt2.state_dict()["state"][0]["exp_avg"], opt.state_dict()["state"][0]["exp_avg"])
    with pytest.raises(CheckpointError, match="'toy' checkpoint, not 'other'"):
        read_config(tmp_path / "ck", "other")
    # the demo export: no training state, half precision, loads back into a float32 model
    export_for_inference(tmp_path / "ck", tmp_path / "small")
    assert not has_training_state(tmp_path / "small")
    assert (tmp_path / "small" / "model.safetensors").stat().st_size < (tmp_path / "ck" / "model.safetensors").stat().st_size
    m3 = _model()
    load_weights(tmp_path / "small", m3)
    assert m3[0].weight.dtype == torch.float32
    torch.testing.assert_close(m3(x), m(x), rtol=1e-2, atol=1e-2)
    export_for_inference(tmp_path / "ck", tmp_path / "small")  # an export replaces an export
    store = tmp_path / "store"  # anything else that exists is left alone: a store, the run's own folder
    store.mkdir()
    (store / "store.json").write_text("{}")
    for dst in (store, tmp_path / "ck"):
        with pytest.raises(CheckpointError, match="is not an exported checkpoint"):
            export_for_inference(tmp_path / "ck", dst)
    assert (store / "store.json").is_file() and has_training_state(tmp_path / "ck")
    with pytest.raises(CheckpointError, match="not a"):
        read_config(tmp_path, "toy")
