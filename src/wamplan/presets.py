"""Every size of the two presets in one place: ``paper`` (the paper's setting) and ``mini`` (this 2-core CPU).

A :class:`Preset` names the world model (encoder, predictor, decoder and their training), TinyWAM and its
training, the data counts per source and the evaluation episode counts. It composes the configs of the
layers below (``worldmodel``, ``wam``), which keep their own defaults and never import this module;
only command-level code (``wamplan wm ...``, ``reproduce``) reads it.

World model, ``paper`` (appendix B, Table 3): DINOv3 ViT-L/16 features (3 views x 196 tokens x 1024),
predictor depth 6, 16 heads x 64, MLP 2048, proprio/action embeddings 64, H_ctx 3, Delta 5, K 2, gamma
0.95, AdamW lr 5e-5 wd 1e-3, batch 24, 24 epochs, 1 warm-up epoch, cosine, clip 1.0; decoder depth 4,
8 heads, width 1024, lr 3e-4, wd 1e-5, batch 16, 24 epochs, 2 warm-up epochs. Not in Table 3, our
choices: the predictor predicts the next frame directly (``predict_delta=False``, as DINO-WM), temporal
RoPE base 100, decoder MLP 4096 and 256 head channels, decoder grad clip 1.0.

World model, ``mini``: the ``patch-pixels`` encoder (64 px, 16 px patches, fixed random projection to 128
dims: 3 views x 16 tokens x 128), Delta 4 (divides the 16-step chunk: 4 rollout steps end exactly at
t+16), a width-128 depth-4 predictor with MLP 384 (0.73 M params) that predicts the change from the
current frame, lr 1e-3, batch 64, 4 epochs (the demo checkpoints' setting); decoder width 192, depth 4,
MLP 768, lr 3e-4, wd 1e-5, batch 32, 8 epochs.

Data (paper §4): 100 expert, 500 noisy, 500 pink-noise (~84 steps each), 500 on-policy episodes; 50
evaluation episodes. ``mini``: 100 expert, 150 noisy, 150 pink-noise (100 steps), 100 on-policy episodes,
a decoder trained on the expert store only, 50 evaluation episodes and 10 for the costly simulator
conditions (2-5).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from wamplan.config import check_numbers
from wamplan.errors import UserError
from wamplan.wam.tinywam_config import TinyWAMConfig
from wamplan.wam.train_config import WAMTrainConfig
from wamplan.worldmodel.config import DecoderConfig, DecoderTrainConfig, PredictorConfig, TrainConfig


@dataclass(frozen=True)
class WorldModelPreset:
    name: str
    encoder: str  # registry name for wamplan.encoders.make_encoder
    encoder_kwargs: dict[str, Any] = field(default_factory=dict)
    predictor: PredictorConfig = field(default_factory=PredictorConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    decoder_train: DecoderTrainConfig = field(default_factory=DecoderTrainConfig)


@dataclass(frozen=True)
class Preset:
    """Everything ``reproduce`` and the ``--preset`` options size."""

    name: str
    world_model: WorldModelPreset
    tinywam: TinyWAMConfig
    tinywam_train: WAMTrainConfig
    # data: episodes per source, pink-noise episode length, image stride of the stores
    expert: int
    noisy: int
    pink: int
    on_policy: int
    pink_max_steps: int
    image_every: int
    decoder_sources: tuple[str, ...]  # the stores the picture decoder learns from (never used for planning)
    # evaluation: episodes of conditions 1, 6, 7 and of the simulator conditions 2-5 (costly on a CPU)
    eval_episodes: int
    sim_eval_episodes: int

    def __post_init__(self) -> None:
        check_numbers(self)
        counts = (self.expert, self.noisy, self.pink, self.on_policy, self.eval_episodes)
        if min(counts) <= 0 or self.sim_eval_episodes < 0:
            raise UserError(f"preset {self.name}: episode counts must be positive, got {counts}")
        if self.world_model.predictor.frameskip % self.image_every or self.tinywam.chunk_length % self.image_every:
            raise UserError(f"preset {self.name}: image_every {self.image_every} must divide the frameskip "
                            f"{self.world_model.predictor.frameskip} and the chunk {self.tinywam.chunk_length}")

    @property
    def wam_epochs(self) -> int:
        return self.tinywam_train.epochs

    @property
    def wm_epochs(self) -> int:
        return self.world_model.train.epochs


WM_PAPER = WorldModelPreset(
    name="paper",
    encoder="dinov3-vitl16",
    encoder_kwargs={"input_size": 224},
    predictor=PredictorConfig(encoder="dinov3-vitl16", num_views=3, num_patches=196, enc_dim=1024,
                              proprio_dim=10, action_dim=5, frameskip=5, context=3, depth=6, heads=16,
                              head_dim=64, mlp_dim=2048, proprio_emb=64, action_emb=64, predict_delta=False),
    train=TrainConfig(horizon=2, gamma=0.95, lr=5e-5, weight_decay=1e-3, batch_size=24, epochs=24,
                      warmup_epochs=1, grad_clip=1.0, log_every_steps=50),
    decoder=DecoderConfig(num_patches=196, enc_dim=1024, image_size=224, width=1024, depth=4, heads=8,
                          mlp_dim=4096, head_channels=256),
    decoder_train=DecoderTrainConfig(lr=3e-4, weight_decay=1e-5, batch_size=16, epochs=24, warmup_epochs=2,
                                     grad_clip=1.0, log_every_steps=50),
)

WM_MINI = WorldModelPreset(
    name="mini",
    encoder="patch-pixels",
    encoder_kwargs={"input_size": 64, "patch_size": 16, "proj_dim": 128, "seed": 0},
    predictor=PredictorConfig(encoder="patch-pixels", num_views=3, num_patches=16, enc_dim=128,
                              proprio_dim=10, action_dim=5, frameskip=4, context=3, depth=4, heads=4,
                              head_dim=32, mlp_dim=384, proprio_emb=64, action_emb=64, predict_delta=True),
    train=TrainConfig(horizon=2, gamma=0.95, lr=1e-3, weight_decay=1e-3, batch_size=64, epochs=4,
                      warmup_epochs=0.5, grad_clip=1.0, log_every_steps=20),
    decoder=DecoderConfig(num_patches=16, enc_dim=128, image_size=64, width=192, depth=4, heads=8,
                          mlp_dim=768, head_channels=128),
    decoder_train=DecoderTrainConfig(lr=3e-4, weight_decay=1e-5, batch_size=32, epochs=8, warmup_epochs=1,
                                     grad_clip=1.0, log_every_steps=20),
)

# TinyWAM (the mini stand-in for Cosmos Policy; the paper preset trains the same network longer)
TINYWAM = TinyWAMConfig(image_size=64, chunk_length=16, channels=(16, 32, 64, 128), latent_dim=256, trunk_dim=512)

PAPER = Preset(name="paper", world_model=WM_PAPER, tinywam=TINYWAM, tinywam_train=WAMTrainConfig(epochs=30),
               expert=100, noisy=500, pink=500, on_policy=500, pink_max_steps=84, image_every=1,
               decoder_sources=("expert", "noisy", "pink", "on_policy"), eval_episodes=50, sim_eval_episodes=50)
MINI = Preset(name="mini", world_model=WM_MINI, tinywam=TINYWAM, tinywam_train=WAMTrainConfig(epochs=12),
              expert=100, noisy=150, pink=150, on_policy=100, pink_max_steps=100, image_every=4,
              decoder_sources=("expert",), eval_episodes=50, sim_eval_episodes=10)

PRESETS: dict[str, Preset] = {p.name: p for p in (PAPER, MINI)}


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise UserError(f"unknown preset '{name}'; choose one of {sorted(PRESETS)}")
    return PRESETS[name]


def get_world_model_preset(name: str) -> WorldModelPreset:
    if name not in PRESETS:
        raise UserError(f"unknown world-model preset '{name}'; choose one of {sorted(PRESETS)}")
    return PRESETS[name].world_model
