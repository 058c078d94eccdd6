"""World-model presets: ``paper`` (appendix B, Table 3) and ``mini`` (this 2-core CPU machine).

``paper``: DINOv3 ViT-L/16 features (3 views x 196 tokens x 1024), predictor depth 6, 16 heads x 64,
MLP 2048, proprio/action embeddings 64, H_ctx 3, Delta 5, K 2, gamma 0.95, AdamW lr 5e-5 wd 1e-3,
batch 24, 24 epochs, 1 warm-up epoch, cosine, clip 1.0; decoder depth 4, 8 heads, width 1024, lr 3e-4,
wd 1e-5, batch 16, 24 epochs, 2 warm-up epochs. Not in Table 3, our choices: the predictor predicts
the next frame directly (``predict_delta=False``, as DINO-WM), temporal RoPE base 100, decoder MLP 4096
and 256 head channels, decoder grad clip 1.0.

``mini``: the ``patch-pixels`` encoder (64 px, 16 px patches, fixed random projection to 128 dims:
3 views x 16 tokens x 128), Delta 4 (divides the 16-step chunk: 4 rollout steps end exactly at t+16),
a width-128 depth-4 predictor with MLP 384 (0.73 M params) that predicts the change from the current
frame, lr 1e-3 (better than 3e-4 on the synthetic task at this size), batch 64, 5 epochs.
Measured on the 2-core CPU while two other jobs used ~1.1 cores (``python -m wamplan.worldmodel.profile
--threads 1``): one CEM plan (32 candidates x 4 iterations x 4 steps, KV-cached) 0.94-1.11 s, naive
re-running 4.4-4.7x slower (MLP 512 took 1.18 s, so it was trimmed; on the quieter box at the start of
the session MLP 512 took ~0.65 s with 2 threads); training ~55 windows/s on 1 thread, i.e. ~6 min per
epoch of 20k windows, ~30 min for the 5 epochs.
When other processes share the 2 cores, use ``torch.set_num_threads(1)``: 2 threads then thrash
(a training step measured 80x slower).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from wamplan.errors import UserError
from wamplan.worldmodel.config import DecoderConfig, PredictorConfig, TrainConfig


@dataclass(frozen=True)
class WorldModelPreset:
    name: str
    encoder: str  # registry name for wamplan.encoders.make_encoder
    encoder_kwargs: dict[str, Any] = field(default_factory=dict)
    predictor: PredictorConfig = field(default_factory=PredictorConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    decoder_train: TrainConfig = field(default_factory=TrainConfig)


PAPER = WorldModelPreset(
    name="paper",
    encoder="dinov3-vitl16",
    encoder_kwargs={"input_size": 224},
    predictor=PredictorConfig(encoder="dinov3-vitl16", num_views=3, num_patches=196, enc_dim=1024,
                              proprio_dim=10, action_dim=5, frameskip=5, context=3, depth=6, heads=16,
                              head_dim=64, mlp_dim=2048, proprio_emb=64, action_emb=64, predict_delta=False),
    train=TrainConfig(horizon=2, gamma=0.95, lr=5e-5, weight_decay=1e-3, batch_size=24, epochs=24,
                      warmup_epochs=1, grad_clip=1.0),
    decoder=DecoderConfig(num_patches=196, enc_dim=1024, image_size=224, width=1024, depth=4, heads=8,
                          mlp_dim=4096, head_channels=256),
    decoder_train=TrainConfig(lr=3e-4, weight_decay=1e-5, batch_size=16, epochs=24, warmup_epochs=2, grad_clip=1.0),
)

MINI = WorldModelPreset(
    name="mini",
    encoder="patch-pixels",
    encoder_kwargs={"input_size": 64, "patch_size": 16, "proj_dim": 128, "seed": 0},
    predictor=PredictorConfig(encoder="patch-pixels", num_views=3, num_patches=16, enc_dim=128,
                              proprio_dim=10, action_dim=5, frameskip=4, context=3, depth=4, heads=4,
                              head_dim=32, mlp_dim=384, proprio_emb=64, action_emb=64, predict_delta=True),
    train=TrainConfig(horizon=2, gamma=0.95, lr=1e-3, weight_decay=1e-3, batch_size=64, epochs=5,
                      warmup_epochs=0.5, grad_clip=1.0),
    decoder=DecoderConfig(num_patches=16, enc_dim=128, image_size=64, width=192, depth=4, heads=8,
                          mlp_dim=768, head_channels=128),
    decoder_train=TrainConfig(lr=3e-4, weight_decay=1e-5, batch_size=32, epochs=8, warmup_epochs=1, grad_clip=1.0),
)

PRESETS: dict[str, WorldModelPreset] = {p.name: p for p in (PAPER, MINI)}


def get_preset(name: str) -> WorldModelPreset:
    if name not in PRESETS:
        raise UserError(f"unknown world-model preset '{name}'; choose one of {sorted(PRESETS)}")
    return PRESETS[name]
