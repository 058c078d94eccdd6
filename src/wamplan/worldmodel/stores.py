"""Training the world model from episode stores: encode the views once (cached beside each store), build
the windows (predictor) or frames (decoder), and train into a run directory; re-running resumes.

The stores of one run hold one task (``data.store.stores_task``): the predictor's views, proprio and action sizes
are that task's and its cameras (the preset's are the cube's), and its checkpoint records the task's name
and the cameras (``config["data"]``; ``load_predictor`` gives them as ``model.task`` and ``model.cameras``).

    train_predictor_on_stores(["data/expert"], "runs/wm", PredictorConfig(...), TrainConfig(...),
                              encoder="patch-pixels", encoder_kwargs={"input_size": 64, ...})
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterator, Sequence

from wamplan.checkpoint import CKPT_DIR, has_training_state
from wamplan.data.features import feature_key
from wamplan.envs.spec import TaskSpec
from wamplan.errors import UserError
from wamplan.worldmodel.config import DecoderConfig, DecoderTrainConfig, PredictorConfig, TrainConfig


def check_image_stride(stores: Sequence[str | Path], frameskip: int) -> None:
    """Every store's image stride must divide the ``frameskip`` (the windows read a frame every Δ steps)."""
    from wamplan.data.store import EpisodeStore, StoreError

    for root in stores:
        every = EpisodeStore(root).image_every
        if frameskip % every:
            raise StoreError(f"frameskip {frameskip} is not a multiple of the store's image stride {every} ({root}); "
                             f"collect with --image-every dividing it or pick --frameskip a multiple of {every}")


def predictor_for_task(cfg: PredictorConfig, task: TaskSpec, cameras: Sequence[str]) -> PredictorConfig:
    """``cfg`` with the views, proprio and action sizes of ``task``'s stores holding ``cameras``."""
    return dataclasses.replace(cfg, num_views=len(cameras), proprio_dim=task.proprio_dim, action_dim=task.action_dim)


def frozen_encoder(name: str, kwargs: dict[str, Any], path: str | None = None, device: str = "auto"):
    """The frozen encoder ``name`` (``path``: local weights for DINOv2/DINOv3) on ``device``."""
    from wamplan.device import resolve_device
    from wamplan.encoders import make_encoder
    from wamplan.encoders.base import encoder_settings

    takes = encoder_settings(name)
    if path and takes is not None and "path" not in takes:
        raise UserError(f"encoder {name} loads no weights: drop --encoder-path (it is for DINOv2/DINOv3)")
    kw = dict(kwargs, **({"path": path} if path else {}))
    return make_encoder(name, **kw).to(resolve_device(device))


def encode_stores(stores: Sequence[str | Path], enc, progress: bool = True) -> None:
    """Cache ``enc``'s features of every episode not yet encoded (``data.features.encode_store``)."""
    from wamplan.progress import progress_bar

    from wamplan.data.features import encode_store
    from wamplan.data.store import EpisodeStore

    for root in stores:
        n = len(EpisodeStore(root).episode_paths())
        for _ in progress_bar(encode_store(root, enc), desc=f"encode {Path(root).name} ({enc.name})", total=n,
                              leave=False, disable=not progress):
            pass


def labelled_models(specs: Sequence[str], stores: Sequence[str | Path]) -> Iterator[tuple[str, Any, str]]:
    """For each ``LABEL=CHECKPOINT`` of ``specs``, in order: its label, the world model (in eval mode) and its
    encoder's feature key, once ``stores`` are encoded in that encoder's features; a spec without a label or a
    checkpoint is refused in one line (before its model loads)."""
    from wamplan.worldmodel.load import load_world_model

    for spec in specs:
        label, sep, ckpt = spec.partition("=")
        if not sep or not label or not ckpt:
            raise UserError(f"{spec!r}: give each model as LABEL=CHECKPOINT, e.g. shipped=checkpoints/mini/wm_augmented")
        model, enc = load_world_model(ckpt)
        encode_stores(stores, enc, progress=False)
        yield label, model.eval(), feature_key(enc.config_dict())


def _setup(stores: Sequence[str | Path], encoder: str, encoder_kwargs: dict[str, Any], encoder_path: str | None,
           device: str, progress: bool):
    if not stores:
        raise UserError("--data needs at least one episode store directory")
    enc = frozen_encoder(encoder, encoder_kwargs, encoder_path, device)
    encode_stores(stores, enc, progress)
    info = enc.config_dict()
    info.pop("path", None)  # where the weights are is not what the model is
    return enc, info


def _prepare(stores: Sequence[str | Path], out: str | Path, kind: str, encoder: str, encoder_kwargs: dict[str, Any],
             encoder_path: str | None, val_fraction: float, device: str, progress: bool):
    """What both trainers do first: the data's identity, the resume decision (checked before any encoding),
    the encoded stores, and the encoder's provenance and feature key."""
    from wamplan.data.store import describe_stores

    if not 0 < val_fraction < 1:
        raise UserError(f"--val-fraction {val_fraction}: the share of episodes held out must be in (0, 1), "
                        f"e.g. 0.1")
    data = dict(describe_stores(stores), val_fraction=val_fraction)
    resume = _resume(out, kind, data)
    enc, info = _setup(stores, encoder, encoder_kwargs, encoder_path, device, progress)
    return data, resume, info, feature_key(enc.config_dict()), (enc.name, enc.num_patches, enc.dim), enc


def _resume(out: str | Path, kind: str, data: dict[str, Any]) -> bool:
    """Whether ``out`` holds a run to resume; refuses one trained on other data before any encoding."""
    from wamplan.train_loop import check_data

    if not has_training_state(Path(out) / CKPT_DIR):
        return False
    check_data(out, kind, data)
    return True


def train_predictor_on_stores(stores: Sequence[str | Path], out: str | Path, predictor: PredictorConfig,
                              train: TrainConfig, *, encoder: str, encoder_kwargs: dict[str, Any],
                              encoder_path: str | None = None, val_fraction: float = 0.1, device: str = "auto",
                              max_steps: int | None = None, progress: bool = True,
                              init: str | Path | None = None) -> dict[str, Any]:
    """Train (or resume) the predictor on the windows of ``stores``; returns the last metrics. ``init``: a
    predictor checkpoint to fine-tune from (``worldmodel.train.train_predictor``)."""
    from wamplan.data.readers import BranchGroups, WorldModelWindows
    from wamplan.data.store import stores_task
    from wamplan.worldmodel.load import KIND
    from wamplan.worldmodel.train import train_predictor

    task, cameras = stores_task(stores)
    check_image_stride(stores, predictor.frameskip)  # before encoding, which may take long
    predictor = predictor_for_task(predictor, task, cameras)
    data, resume, info, key, (name, n, d), _ = _prepare(stores, out, KIND, encoder, encoder_kwargs, encoder_path,
                                                          val_fraction, device, progress)
    predictor = dataclasses.replace(predictor, encoder=name, num_patches=n, enc_dim=d)  # the encoder's token layout
    kw = dict(frameskip=predictor.frameskip, history=predictor.context, horizon=train.horizon,
              features=key, val_fraction=val_fraction, window_end=train.window_end)
    tr, va = WorldModelWindows(stores, split="train", **kw), WorldModelWindows(stores, split="val", **kw)
    if progress:
        print(f"windows: {len(tr)} train, {len(va)} val ({len(tr.episodes)} / {len(va.episodes)} episodes)")
        if not len(va):
            print(f"note: --val-fraction {val_fraction:g} held out no episode of these {len(tr.episodes)} (each is "
                  f"held out by a hash of its name), so nothing is scored held-out; raise it or add episodes")
    groups = val_groups = None
    if train.sibling_weight > 0:
        groups, val_groups = (BranchGroups(stores, predictor.frameskip, predictor.context, train.sibling_horizon,
                                           split=split, val_fraction=val_fraction, features=key)
                              for split in ("train", "val"))
        if len(groups) < train.sibling_groups:
            raise UserError(f"--sibling-weight {train.sibling_weight} needs at least --sibling-groups "
                            f"{train.sibling_groups} groups of counterfactual branches in the training split of --data "
                            f"(`wamplan collect --source policy --branches N --branch-context "
                            f"{(predictor.context - 1) * predictor.frameskip}`); found {len(groups)}: collect more "
                            f"parents or lower --sibling-groups")
        if progress:
            print(f"branch groups: {len(groups)} train, {len(val_groups)} val, of {groups.group} siblings")
    _, metrics = train_predictor(tr, predictor, train, out, val_set=va if len(va) else None, device=device,
                                 resume=resume, max_steps=max_steps, progress=progress, encoder_info=info,
                                 data=data, init=init, group_set=groups, val_groups=val_groups, task=task,
                                 cameras=cameras)
    return metrics


def train_decoder_on_stores(stores: Sequence[str | Path], out: str | Path, decoder: DecoderConfig,
                            train: DecoderTrainConfig, *, encoder: str, encoder_kwargs: dict[str, Any],
                            encoder_path: str | None = None, val_fraction: float = 0.1, device: str = "auto",
                            max_steps: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) the picture decoder on the (features, image) frames of ``stores`` (of one task)."""
    from wamplan.data.readers import FeatureFrames
    from wamplan.data.store import stores_task
    from wamplan.worldmodel.decoder import KIND, train_decoder

    task, cameras = stores_task(stores)
    data, resume, info, key, (_, n, d), _ = _prepare(stores, out, KIND, encoder, encoder_kwargs, encoder_path,
                                                  val_fraction, device, progress)
    decoder = dataclasses.replace(decoder, num_patches=n, enc_dim=d)  # the encoder's token layout
    tr = FeatureFrames(stores, key, split="train", val_fraction=val_fraction)
    va = FeatureFrames(stores, key, split="val", val_fraction=val_fraction)
    if progress:
        print(f"frames: {len(tr)} train, {len(va)} val")
    _, metrics = train_decoder(tr, decoder, train, out, val_set=va if len(va) else None, device=device,
                               resume=resume, max_steps=max_steps, progress=progress, encoder_info=info,
                               data=data, task=task.name, cameras=cameras)
    return metrics
