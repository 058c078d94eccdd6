"""A ``concat`` world model whose parts are predicted by other models: the spliced predictor.

A concat encoder stacks its parts' tokens along the feature axis, part i scaled by s_i: z = [s_0 z_0 | s_1 z_1 | ...]
(D = sum D_i). A concat model (the *base*) predicts all D dims with one network. Splicing keeps the base for some
parts and takes the others from models trained on that part's encoder alone (the *part models*): part i's dims of
every output are s_i times its part model's prediction, made from the context's part-i tokens with the scale undone.
Each model rolls out on its own predictions, so the spliced prediction of part i is exactly what its part model
predicts, and the base's other dims exactly the base's; the proprio prediction is the base's.

E.g. the shipped patch-pixels model kept, bit for bit, for the first part of a model grown onto learned features:
the planning cost (a mean over all D dims) then adds the learned dims' error to exactly what shipped plans with.

A spliced checkpoint is one ordinary checkpoint directory of kind ``wm-splice``: every model's weights in one
``model.safetensors`` (``base.*``, ``parts.<i>.*``), each model's own config record in ``config.json``.
``worldmodel.load.load_world_model`` loads it like any world model; ``worldmodel.reweigh.splice_parts`` makes one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from wamplan.checkpoint import load_weights, read_config
from wamplan.errors import UserError
from wamplan.worldmodel.predictor import PrefixCache, WorldModelPredictor, without_retired

SPLICE_KIND = "wm-splice"
SHARED = ("frameskip", "context", "num_views", "num_patches", "proprio_dim", "action_dim")  # cfg fields all share


@dataclass
class SplicedPrefix:
    """The base's cached context and each part model's, by part index."""

    base: PrefixCache
    parts: dict[int, PrefixCache]


class SplicedPredictor(nn.Module):
    """``base`` (a predictor over concat tokens of parts with dims ``dims`` and scales ``scales``) with part i's
    predictions taken from ``parts[i]`` (a predictor over part i's own tokens, D_i dims). The predictor API of
    :class:`WorldModelPredictor` that planning and evaluation use: ``forward``, ``encode_prefix``,
    ``rollout_from_prefix``, ``rollout``, ``cfg``/``task``/``cameras`` (the base's)."""

    def __init__(self, base: WorldModelPredictor, parts: dict[int, WorldModelPredictor],
                 dims: list[int], scales: list[float]) -> None:
        super().__init__()
        if len(dims) != len(scales) or sum(dims) != base.cfg.enc_dim:
            raise UserError(f"the base predicts {base.cfg.enc_dim} dims, the parts' dims {dims} sum to {sum(dims)}; "
                            f"splice parts of the base's own concat encoder")
        if not parts:
            raise UserError("a splice needs at least one part model; give {part index: model}")
        for i, m in parts.items():
            if not 0 <= i < len(dims):
                raise UserError(f"part {i} asked for, the base's encoder has {len(dims)} parts (0-{len(dims) - 1})")
            if m.cfg.enc_dim != dims[i]:
                raise UserError(f"the model for part {i} predicts {m.cfg.enc_dim} dims, the part has {dims[i]}; "
                                f"give a model trained on that part's encoder")
            differ = [f for f in SHARED if getattr(m.cfg, f) != getattr(base.cfg, f)]
            if differ:
                raise UserError(f"the model for part {i} differs from the base in {', '.join(differ)}; splice "
                                f"models trained on one task's frames at one frameskip and context")
            if m.cameras and base.cameras and tuple(m.cameras) != tuple(base.cameras):
                raise UserError(f"the model for part {i} predicts views {list(m.cameras)}, the base "
                                f"{list(base.cameras)}; splice models trained on the same cameras in the same order")
        self.base = base
        self.parts = nn.ModuleDict({str(i): parts[i] for i in sorted(parts)})
        self.dims, self.scales = list(dims), [float(s) for s in scales]
        self.cfg, self.task = base.cfg, base.task

    @property
    def cameras(self) -> tuple[str, ...] | None:
        return self.base.cameras

    def _part(self, i: int) -> tuple[int, int, float]:
        start = sum(self.dims[:i])
        return start, start + self.dims[i], self.scales[i]

    def _own(self, z: torch.Tensor, i: int) -> torch.Tensor:
        """Concat tokens (..., D) -> part i's own tokens (..., D_i), its scale undone."""
        start, stop, scale = self._part(i)
        return z[..., start:stop] / scale

    def _join(self, z: torch.Tensor, own: dict[int, torch.Tensor]) -> torch.Tensor:
        """The base's prediction (..., D) with part i's dims replaced by scale_i * own[i] (..., D_i)."""
        pieces, at = [], 0
        for i in sorted(own):
            start, stop, scale = self._part(i)
            pieces += [z[..., at:start], own[i].to(z.dtype) * scale]
            at = stop
        return torch.cat(pieces + [z[..., at:]], dim=-1)  # (..., D)

    def _models(self):
        return [(int(i), m) for i, m in self.parts.items()]

    def forward(self, z: torch.Tensor, q: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Teacher-forced, as :meth:`WorldModelPredictor.forward`: z (B, T, V, N, D), q (B, T, P), a (B, T, Δ·A)."""
        zb, qb = self.base(z, q, a)  # (B, T, V, N, D), (B, T, P)
        return self._join(zb, {i: m(self._own(z, i), q, a)[0] for i, m in self._models()}), qb

    def encode_prefix(self, z: torch.Tensor, q: torch.Tensor, a: torch.Tensor) -> SplicedPrefix:
        """Every model's cache of the context frames before the current one (shapes as the base's)."""
        return SplicedPrefix(self.base.encode_prefix(z, q, a),
                             {i: m.encode_prefix(self._own(z, i), q, a) for i, m in self._models()})

    def rollout_from_prefix(self, prefix: SplicedPrefix, z_cur: torch.Tensor, q_cur: torch.Tensor,
                            a_future: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z_cur (Bc, V, N, D), q_cur (Bc, P), a_future (B, S, Δ·A) -> z (B, S, V, N, D), q (B, S, P)."""
        zb, qb = self.base.rollout_from_prefix(prefix.base, z_cur, q_cur, a_future)
        own = {i: m.rollout_from_prefix(prefix.parts[i], self._own(z_cur, i), q_cur, a_future)[0]
               for i, m in self._models()}
        return self._join(zb, own), qb

    def rollout(self, z_ctx: torch.Tensor, q_ctx: torch.Tensor, a_ctx_past: torch.Tensor,
                a_future: torch.Tensor, naive: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`WorldModelPredictor.rollout`: every model rolls out on its own predictions."""
        zb, qb = self.base.rollout(z_ctx, q_ctx, a_ctx_past, a_future, naive)
        own = {i: m.rollout(self._own(z_ctx, i), q_ctx, a_ctx_past, a_future, naive)[0] for i, m in self._models()}
        return self._join(zb, own), qb

    def compile_blocks(self, backend: Any = "inductor") -> "SplicedPredictor":
        """Every model's blocks through ``torch.compile`` (:meth:`WorldModelPredictor.compile_blocks`). Returns self."""
        for m in [self.base, *self.parts.values()]:
            m.compile_blocks(backend)
        return self

    def num_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


def spliced_record(model: SplicedPredictor, base: dict[str, Any], parts: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """The ``config`` of the spliced checkpoint of ``model`` from the base's and the part models' own config records:
    the base's encoder and data (what the spliced model reads and was trained on), the parts' dims and scales, and
    every model's record."""
    return {"encoder": base.get("encoder"), "data": base.get("data"), "dims": model.dims, "scales": model.scales,
            "base": base, "parts": {str(i): rec for i, rec in sorted(parts.items())}}


def load_spliced(ckpt: str | Path, device: str | torch.device = "cpu") -> SplicedPredictor:
    """The spliced predictor (eval mode) of the checkpoint directory ``ckpt`` (kind ``wm-splice``) on ``device``."""
    saved = read_config(ckpt, SPLICE_KIND)
    parts = saved.get("parts")
    if not isinstance(saved.get("base"), dict) or not isinstance(parts, dict) or not parts or \
            not isinstance(saved.get("dims"), list) or not isinstance(saved.get("scales"), list):
        raise UserError(f"{ckpt}: a spliced checkpoint records its base, its part models, and the parts' dims and "
                        f"scales; this one does not (damaged?): splice the models again "
                        f"(worldmodel.reweigh.splice_parts)")
    model = SplicedPredictor(WorldModelPredictor.from_record(saved["base"]),
                             {int(i): WorldModelPredictor.from_record(rec) for i, rec in parts.items()},
                             saved["dims"], saved["scales"])
    load_weights(ckpt, model, adapt=without_retired)
    return model.to(device).eval()
