"""The world model (paper §3.2): a block-causal ViT predictor over frozen patch features, a pixel
decoder for inspection and their training (the ``paper``/``mini`` sizes live in ``wamplan.presets``).

    from wamplan.worldmodel import load_predictor
    wm = load_predictor("runs/wm")                                  # eval mode
    prefix = wm.encode_prefix(z[:, :2], q[:, :2], a_past)          # once per chunk, batch 1
    z_pred, q_pred = wm.rollout_from_prefix(prefix, z[:, 2], q[:, 2], a_cand)  # (C, S, ...)
"""

from wamplan.worldmodel.config import DecoderConfig, DecoderTrainConfig, PredictorConfig, TrainConfig
from wamplan.worldmodel.decoder import Decoder, evaluate_decoder, load_decoder, train_decoder
from wamplan.worldmodel.predictor import PrefixCache, WorldModelPredictor, action_blocks
from wamplan.worldmodel.train import (compute_feature_stats, evaluate_predictor, load_predictor, train_predictor,
                                      window_loss)

__all__ = ["action_blocks", "DecoderConfig", "DecoderTrainConfig", "PredictorConfig", "TrainConfig", "Decoder",
           "PrefixCache", "WorldModelPredictor", "compute_feature_stats",
           "evaluate_decoder", "evaluate_predictor", "load_decoder", "load_predictor", "train_decoder",
           "train_predictor", "window_loss"]
