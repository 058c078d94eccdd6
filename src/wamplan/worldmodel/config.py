"""Configs of the world model: the predictor and the decoder, and the training of each.

Frozen dataclasses validated in ``__post_init__``; field help strings are the ``--help`` text
(``wamplan.config.add_arguments``). The ``paper`` and ``mini`` values live in ``wamplan/presets.py``.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any

from wamplan.config import (ConfigError, add_field_argument, as_options, check_numbers, field, from_dict,
                            preset_default_text, require)
from wamplan.train_config import AdamWConfig

ACTION_CONDITIONING = ("input", "adaln")  # PredictorConfig.action_conditioning
# The task of a world-model checkpoint that records none: every one made before tasks was trained on it.


@dataclass(frozen=True)
class PredictorConfig:
    """Block-causal ViT over the patch tokens of V views x H_ctx frames (paper §3.2, Table 3).

    Width (heads x head_dim), depth and the MLP are options (``wamplan wm train --depth/--heads/--head-dim/
    --mlp-dim``, :data:`ARCHITECTURE_FIELDS`), and so are the variants ``action_conditioning`` and
    ``action_tokens``; every default is the model the shipped checkpoints are.

    One token grid (N) for all V views, not one per view: the (V, N, D) layout that the encoders, feature caches,
    costs, WAM and decoder share would turn ragged.
    """

    encoder: str = field("patch-pixels", "registry name of the frozen encoder whose features this predicts")
    num_views: int = field(3, "V, camera views per frame (front, side, wrist)")
    num_patches: int = field(16, "N, patch tokens per view (the encoder's num_patches)")
    enc_dim: int = field(128, "D_enc, feature size of one patch token (the encoder's dim)")
    proprio_dim: int = field(10, "P, proprioception size")
    action_dim: int = field(5, "A, action size of one control step")
    frameskip: int = field(4, "Delta, control steps between frames; one frame carries Delta*A actions")
    context: int = field(3, "H_ctx, frames in the attention window (current + H_ctx-1 previous)")
    depth: int = field(4, "transformer blocks")
    heads: int = field(4, "attention heads")
    head_dim: int = field(32, "size of one head; model width = heads * head_dim")
    mlp_dim: int = field(512, "hidden size of each block's MLP")
    proprio_emb: int = field(64, "output size of the proprioception MLP projector")
    action_emb: int = field(64, "output size of the action-block MLP projector")
    rope_base: float = field(100.0, "base of the temporal rotary embedding (frequencies base^-i, i in [0,1))")
    predict_delta: bool = field(True, "predict the change from the current frame (True) or the next frame itself")
    dropout: float = field(0.0, "dropout in attention output and MLP")
    action_conditioning: str = field("input", "where the action block enters: 'input' (its embedding joins every "
                                              "token of its frame at the input, once) or 'adaln' (also an adaptive "
                                              "layer norm in every block: shift, scale and gate of the attention and "
                                              "MLP branches from the frame's action embedding, zero-initialised as in "
                                              "DiT's adaLN-Zero, so every block starts as the identity)")
    action_tokens: bool = field(False, "also give each frame Delta tokens of its own, one per control step of its "
                                       "action block (that step's action through an MLP plus a learned step "
                                       "embedding), which its visual tokens attend to; nothing reads them out")

    def __post_init__(self) -> None:
        check_numbers(self)
        for name in ("num_views", "num_patches", "enc_dim", "proprio_dim", "action_dim", "frameskip",
                     "context", "depth", "heads", "head_dim", "mlp_dim", "proprio_emb", "action_emb"):
            v = getattr(self, name)
            require(isinstance(v, int) and v > 0, f"PredictorConfig.{name} must be a positive int, got {v!r}")
        require(self.head_dim % 2 == 0, f"PredictorConfig.head_dim must be even (rotary pairs), got {self.head_dim}")
        require(self.rope_base > 1.0, f"PredictorConfig.rope_base must be > 1, got {self.rope_base}")
        require(0.0 <= self.dropout < 1.0, f"PredictorConfig.dropout must be in [0, 1), got {self.dropout}")
        require(bool(self.encoder), "PredictorConfig.encoder must name the encoder (e.g. patch-pixels)")
        require(self.action_conditioning in ACTION_CONDITIONING,
                f"PredictorConfig.action_conditioning must be one of {list(ACTION_CONDITIONING)}, "
                f"got {self.action_conditioning!r}")

    @property
    def width(self) -> int:
        """Model width d = heads * head_dim."""
        return self.heads * self.head_dim

    @property
    def tokens_per_frame(self) -> int:
        """M = V * N visual tokens per frame."""
        return self.num_views * self.num_patches

    @property
    def action_block_dim(self) -> int:
        """Delta * A, the size of one frame's action block."""
        return self.frameskip * self.action_dim

    @property
    def frame_tokens(self) -> int:
        """M' = M visual tokens (+ Delta action tokens with ``action_tokens``): one frame's tokens in the sequence."""
        return self.tokens_per_frame + (self.frameskip if self.action_tokens else 0)


# Keys of PredictorConfig that older checkpoints stored and this version no longer has: the spread head's and the state
# head's (removed: no measured gain; the lab's table keeps their records). Loading drops them, and the heads' weights
# (``worldmodel.predictor.without_retired``).
RETIRED_PREDICTOR_KEYS = ("spread_head", "state_dim", "state_head")


def predictor_config(record: dict[str, Any]) -> PredictorConfig:
    """The :class:`PredictorConfig` of a checkpoint's ``predictor`` record, without :data:`RETIRED_PREDICTOR_KEYS`
    (other unknown keys are refused, as :func:`~wamplan.config.from_dict` does)."""
    return from_dict(PredictorConfig, {k: v for k, v in record.items() if k not in RETIRED_PREDICTOR_KEYS})


# The predictor's fields that `wamplan wm train` may override on top of a preset (the rest, the encoder's token
# layout, are fixed by the encoder). ``frameskip`` must be a multiple of the stores' image stride (the readers
# refuse it otherwise); to plan, it must not exceed the WAM's chunk (``planning.policy_config.check_frameskip``).
# Δ = the chunk (16 for the cube task) makes the history the chunk boundaries alone: t-2H, t-H, t with context 3.
ARCHITECTURE_FIELDS = ("frameskip", "context", "depth", "heads", "head_dim", "mlp_dim", "proprio_emb", "action_emb",
                       "dropout", "predict_delta", "action_conditioning", "action_tokens")


def add_architecture_arguments(parser: Any, presets: dict[str, PredictorConfig] | None = None) -> None:
    """One ``--<field>`` option per :data:`ARCHITECTURE_FIELDS` entry (default None: keep the preset's);
    ``presets`` ({name: predictor config}): their values shown in the help."""
    hints = typing.get_type_hints(PredictorConfig)
    fields = {f.name: f for f in dataclasses.fields(PredictorConfig)}
    for name in ARCHITECTURE_FIELDS:
        add_field_argument(parser, "--" + name.replace("_", "-"), name, fields[name], hints[name],
                           default_text=preset_default_text(name, presets))


def architecture_from_args(args: Any, base: PredictorConfig) -> PredictorConfig:
    """``base`` with the architecture options the user passed (those not None)."""
    changes = {k: getattr(args, k) for k in ARCHITECTURE_FIELDS if getattr(args, k, None) is not None}
    try:
        return dataclasses.replace(base, **changes)
    except ConfigError as e:  # named by the options, as from_args names them
        raise ConfigError(as_options(str(e), type(base).__name__,
                                     {k: "--" + k.replace("_", "-") for k in ARCHITECTURE_FIELDS})) from None


@dataclass(frozen=True)
class DecoderConfig:
    """ViT over one view's patch tokens with a convolutional upsampling head to pixels."""

    num_patches: int = field(16, "N, patch tokens of one view (a square grid)")
    enc_dim: int = field(128, "D_enc, feature size of one patch token")
    image_size: int = field(64, "side of the square output image; image_size / sqrt(N) must be a power of 2")
    width: int = field(256, "transformer width")
    depth: int = field(4, "transformer blocks")
    heads: int = field(8, "attention heads")
    mlp_dim: int = field(1024, "hidden size of each block's MLP")
    head_channels: int = field(128, "channels of the first upsampling stage (halved each stage, min 16)")

    def __post_init__(self) -> None:
        check_numbers(self)
        for name in ("num_patches", "enc_dim", "image_size", "width", "depth", "heads", "mlp_dim",
                     "head_channels"):
            v = getattr(self, name)
            require(isinstance(v, int) and v > 0, f"DecoderConfig.{name} must be a positive int, got {v!r}")
        g = int(round(self.num_patches ** 0.5))
        require(g * g == self.num_patches, f"DecoderConfig.num_patches must be a square grid, got {self.num_patches}")
        up = self.image_size // g
        require(self.image_size % g == 0 and up & (up - 1) == 0,
                f"DecoderConfig.image_size / grid must be a power of 2; got {self.image_size} / {g}; "
                f"pick image_size = {g} * 2**k")
        require(self.width % self.heads == 0,
                f"DecoderConfig.width {self.width} must be divisible by heads {self.heads}")

    @property
    def grid(self) -> int:
        return int(round(self.num_patches ** 0.5))


@dataclass(frozen=True)
class DecoderTrainConfig(AdamWConfig):
    """Optimisation of the decoder: the loop's fields and AdamW's betas (:class:`~wamplan.train_loop.AdamWConfig`);
    none of the predictor's loss, window or sibling fields."""


# Keys of TrainConfig that older runs stored and this version no longer has: the ranking loss's, the spread head's and
# the state head's (removed: none measured a gain; the lab's table keeps their records). A resumed run and a saved
# config ignore them (a run that trained a spread or state head is refused: ``worldmodel.train``).
RETIRED_TRAIN_KEYS = ("rank_temperature", "rank_wam", "rank_weight", "spread_only", "spread_weight", "state_weight")


@dataclass(frozen=True)
class TrainConfig(AdamWConfig):
    """Optimisation of the predictor: the loop's fields and AdamW's betas (:class:`~wamplan.train_loop.AdamWConfig`),
    eq. 2's K-step discounted loss, where an episode's windows end, and the optional sibling and ranking losses on
    counterfactual branch groups."""

    horizon: int = field(2, "K, autoregressive prediction steps per window (windows hold H_ctx + K frames)")
    gamma: float = field(0.95, "discount of step h's loss: gamma**(h-1)")
    loss_form: str = field("mean", "eq. 2's terms: 'mean' (per-element MSE of z plus that of q) or 'sum' (the "
                                   "paper's squared norms, ||dz||^2 + ||dq||^2, divided by z's size)")
    window_end: str = field("block", "last window of an episode: 'block' (the last frame's action block lies in "
                                     "the episode) or 'frame' (the last frame may be the episode's last Δ-grid frame)")
    sibling_weight: float = field(0.0, "weight of the sibling loss on counterfactual branch groups (0: off): the "
                                       "error of each branch's predicted future relative to its siblings' mean")
    sibling_horizon: int = field(4, "frames the sibling windows predict into the branch's chunk (chunk / Δ: the "
                                    "frames the planner's cost looks at)")
    sibling_groups: int = field(8, "branch groups (of --branches siblings each) per optimisation step")
    change_weight: float = field(0.0, "weigh each token's latent error by how much that token changes: weight "
                                      "1 + W * (its squared change from the current frame) / (the mean of that "
                                      "over the window's tokens), divided by 1 + W so the loss keeps its scale "
                                      "(0: off, every token weighs the same)")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(self.horizon >= 1, f"TrainConfig.horizon (K) must be >= 1, got {self.horizon}")
        require(0.0 < self.gamma <= 1.0, f"TrainConfig.gamma must be in (0, 1], got {self.gamma}")
        require(self.loss_form in ("mean", "sum"), f"TrainConfig.loss_form must be mean or sum, got {self.loss_form!r}")
        require(self.window_end in ("block", "frame"),
                f"TrainConfig.window_end must be block or frame, got {self.window_end!r}")
        require(self.sibling_weight >= 0, f"TrainConfig.sibling_weight must be >= 0, got {self.sibling_weight}")
        require(self.sibling_horizon >= 1, f"TrainConfig.sibling_horizon must be >= 1, got {self.sibling_horizon}")
        require(self.sibling_groups >= 1, f"TrainConfig.sibling_groups must be >= 1, got {self.sibling_groups}")
        require(self.change_weight >= 0, f"TrainConfig.change_weight must be >= 0 (0: off), got {self.change_weight}")

