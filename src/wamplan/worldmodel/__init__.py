"""The world model (paper §3.2): a block-causal ViT predictor over frozen patch features, a pixel
decoder for inspection, their training and their loading (the ``paper``/``mini`` sizes live in ``wamplan.presets``).

    from wamplan.worldmodel import load_predictor
    wm = load_predictor("runs/wm")                                  # eval mode
    prefix = wm.encode_prefix(z[:, :2], q[:, :2], a_past)          # once per chunk, batch 1
    z_pred, q_pred = wm.rollout_from_prefix(prefix, z[:, 2], q[:, 2], a_cand)  # (C, S, ...)

The names below are loaded on first use, so that loading a world model (``worldmodel.load``) does not import its
training.
"""

from __future__ import annotations

from wamplan.registry import lazy_exports

_HOMES = {
    "config": ("DecoderConfig", "DecoderTrainConfig", "PredictorConfig", "TrainConfig"),
    "decoder": ("Decoder", "evaluate_decoder", "load_decoder", "train_decoder"),
    "predictor": ("PrefixCache", "WorldModelPredictor", "action_blocks"),
    "load": ("load_predictor",),
    "losses": ("window_loss",),
    "train": ("compute_feature_stats", "evaluate_predictor", "train_predictor"),
}
__getattr__, __all__ = lazy_exports(__name__, _HOMES)
