"""``--log tensorboard wandb`` (wamplan.train_log): the scalars of metrics.jsonl read back, under the same names and at
the same steps, from the TensorBoard event file and from the W&B offline run's .wandb file; the trainers' pictures;
a missing package refused in one line before training."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from wamplan.cli import main

pytestmark = pytest.mark.usefixtures("one_thread")
tensorboard = pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed "
                                                        "(pip install 'wamplan[tensorboard]')")
TINY_WAM = ["--image-size", "32", "--channels", "8", "16", "--latent-dim", "32", "--trunk-dim", "64"]


def _metrics(run: Path) -> list[dict]:
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]


def _names(records: list[dict]) -> set[str]:
    """The curve names a metrics.jsonl holds: every number but the step."""
    return {k for r in records for k, v in r.items() if k != "global_step" and isinstance(v, (int, float))}


def _tensorboard(run: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    return acc


def _wandb_rows(run: Path) -> list[dict]:
    """The history rows of the W&B offline run in ``run``: its .wandb file is a LevelDB-style log (a 7-byte
    ':W&B' header, then 32 KiB blocks of records, each a 7-byte header: crc, length, kind) of wandb's own protobuf
    ``Record`` messages. wandb 0.31 ships no Python reader of it, so the framing is read here and every record is
    parsed with wandb's protobuf classes."""
    from wandb.proto import wandb_internal_pb2

    (path,) = (run / "wandb").glob("offline-run-*/run-*.wandb")
    data, block = path.read_bytes(), 32768
    assert data[:4] == b":W&B"
    pos, pending, rows = 7, b"", []
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        _, n, kind = struct.unpack("<IHB", data[pos:pos + 7])
        pending, pos = pending + data[pos + 7:pos + 7 + n], pos + 7 + n
        if kind in (1, 4):  # a full record, or the last piece of one
            rec = wandb_internal_pb2.Record()
            rec.ParseFromString(pending)
            pending = b""
            if rec.WhichOneof("record_type") == "history":
                rows.append({i.key or "/".join(i.nested_key): json.loads(i.value_json) for i in rec.history.item})
    return rows


class Toy:
    """16 random items of 3 numbers."""

    def __len__(self):
        return 16

    def epoch(self, indices, batch_size, first_step):
        g = torch.Generator().manual_seed(first_step)
        return [torch.randn(batch_size, 3, generator=g) for _ in range(len(indices) // batch_size)]


PICTURE = np.arange(8 * 16 * 3, dtype=np.uint8).reshape(8, 16, 3)


def _fit_toy(run: Path, epochs: int, log: tuple[str, ...], resume: bool = False) -> None:
    """A linear model fitted by the loop into ``run``: 4 steps an epoch, a step record every 2, a picture an epoch."""
    from wamplan.train_config import LoopConfig
    from wamplan.train_loop import fit

    torch.manual_seed(0)
    cfg = LoopConfig(epochs=epochs, batch_size=4, lr=1e-2, log_every_steps=2, log=log)
    step = lambda m, b: (m(b).square().mean(), {"abs": float(m(b).detach().abs().mean())})  # noqa: E731
    fit(torch.nn.Linear(3, 1), Toy(), step, cfg, run_dir=run, kind="toy", config={"train": {}}, resume=resume,
        evaluate=lambda m: {"err": 0.5}, progress=False, log=None, pictures=lambda m: {"val/picture": PICTURE})


def test_fit_sends_every_metrics_scalar_to_tensorboard_and_wandb(tmp_path):
    run = tmp_path / "run"
    _fit_toy(run, 2, ("tensorboard", "wandb"))
    records = _metrics(run)
    names = _names(records)
    assert names == {"epoch", "lr", "train/loss", "train/abs", "samples_per_s", "val/err"}

    tb = _tensorboard(run)
    assert set(tb.Tags()["scalars"]) == names and tb.Tags()["images"] == ["val/picture"]
    for name in names:  # every value at its step, step records and epoch records alike (float32 in the file)
        want = [(r["global_step"], r[name]) for r in records if name in r]
        got = [(e.step, e.value) for e in tb.Scalars(name)]
        assert [s for s, _ in got] == [s for s, _ in want]
        np.testing.assert_allclose([v for _, v in got], [v for _, v in want], rtol=1e-6)
    assert [e.step for e in tb.Images("val/picture")] == [4, 8]

    rows = _wandb_rows(run)
    drawn = [r for r in rows if "val/picture/path" in r]  # an image is a nested value: its file, size, ...
    scalar_rows = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows if r not in drawn]
    assert scalar_rows == [{k: v for k, v in r.items() if k != "event"} for r in records]  # one row a record
    assert [r["global_step"] for r in drawn] == [4, 8] and drawn[0]["val/picture/width"] == 16
    assert len(list((run / "wandb").glob("offline-run-*/files/media/images/val/picture_*.png"))) == 2


def test_a_resumed_run_keeps_its_tensorboard_curves_up_to_the_checkpoint(tmp_path):
    """Resuming drops only the events logged after the checkpoint (none here): the saved epoch's end stays."""
    run = tmp_path / "run"
    _fit_toy(run, 1, ("tensorboard",))
    _fit_toy(run, 2, ("tensorboard",), resume=True)
    records, tb = _metrics(run), _tensorboard(run)
    assert [r["global_step"] for r in records] == [2, 4, 4, 6, 8, 8]
    assert [e.step for e in tb.Scalars("train/loss")] == [2, 4, 4, 6, 8, 8]
    assert [e.step for e in tb.Images("val/picture")] == [4, 8]


@pytest.fixture(scope="module")
def store(tmp_path_factory, expert_store):
    """A copy of the session's 2-episode expert store (`wm train` caches features in it)."""
    return shutil.copytree(expert_store, tmp_path_factory.mktemp("train_log") / "expert")


@pytest.mark.parametrize("command, extra, pictures", [
    (["wm", "train-decoder"], ["--log", "tensorboard", "wandb"], ["val/decoded_vs_target"]),
    (["wam", "train"], ["--log", "tensorboard", "--no-progress", *TINY_WAM], ["val/predicted_vs_future"]),
    (["wm", "train"], ["--log", "tensorboard"], []),  # the predictor alone draws nothing: no decoder in its run
])
def test_the_trainers_log_their_metrics_names_and_pictures(store, tmp_path, command, extra, pictures):
    run = tmp_path / "run"
    assert main([*command, "--data", str(store), "--out", str(run), "--epochs", "1", "--batch-size", "8",
                 "--device", "cpu", *extra]) == 0
    names = _names(_metrics(run))
    assert {"lr", "train/loss", "samples_per_s"} <= names and any(n.startswith("val/") for n in names)
    tb = _tensorboard(run)
    assert set(tb.Tags()["scalars"]) == names and tb.Tags()["images"] == pictures
    for tag in pictures:  # each row: the prediction beside its target, as wide as two views
        (event,) = tb.Images(tag)
        assert event.width == 2 * event.height // 4
    if "wandb" in extra:
        keys = {k for r in _wandb_rows(run) for k in r if not k.startswith("_")}
        assert {k for k in keys if not k.startswith(tuple(pictures))} == names | {"global_step"}
        assert all(f"{p}/path" in keys for p in pictures)


def test_a_missing_logger_package_is_one_line_before_training(store, tmp_path, monkeypatch, refused, capsys):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else find_spec(name, *a))
    for command in (["wam", "train", "--no-progress", *TINY_WAM], ["wm", "train"], ["wm", "train-decoder"]):
        out = tmp_path / command[1]
        refused([*command, "--data", store, "--out", out, "--epochs", "1", "--log", "tensorboard", "wandb"],
                "--log wandb needs the wandb package", "pip install 'wamplan[wandb]'")
        assert not out.exists()  # nothing read, encoded or trained
    with pytest.raises(SystemExit, match="2"):  # argparse refuses an unknown logger, listing the two
        main(["wm", "train", "--data", str(store), "--out", str(tmp_path / "x"), "--log", "mlflow"])
    assert "invalid choice: 'mlflow' (choose from 'tensorboard', 'wandb')" in capsys.readouterr().err
