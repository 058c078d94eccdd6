"""``concat``: the tokens of several frozen encoders side by side, one token grid.

    enc = make_encoder("concat", parts=[{"name": "patch-pixels"},
                                        {"name": "task-cnn", "ckpt": "runs/enc"}],  # a trained task-cnn
                       scales=[1.0, 0.366])
    z = enc.encode(images)              # (B, 16, 128 + 128): part 0's dims first, then part 1's

Each part sees the uint8 images itself (its own resize and normalisation); the parts must give the same number
of tokens N, laid out the same way. ``scales`` (one per part, default 1) multiply each part's tokens, so the
planning cost, a plain mean over dims, weighs the parts as chosen (e.g. equal per-dim variance on a store).

A world model trained on ``patch-pixels`` can be grown onto a ``concat`` whose first part is that same
encoder at scale 1 (``wm train --init``, ``worldmodel.grow``): it starts predicting the first part's dims
exactly as before.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch

from wamplan.encoders.base import FrozenEncoder, make_encoder, register_encoder
from wamplan.errors import UserError


@register_encoder("concat")
class ConcatEncoder(FrozenEncoder):
    """``parts``: encoder configs ``{"name": ..., **settings}`` (at least one, none a ``concat``); ``scales``:
    a positive factor per part (default all 1). Tokens (B, N, sum of the parts' D)."""

    name = "concat"

    def __init__(self, parts: Sequence[dict[str, Any]] | None = None,
                 scales: Sequence[float] | None = None) -> None:
        if not parts or not isinstance(parts, (list, tuple)) or not all(isinstance(p, dict) and p.get("name")
                                                                         for p in parts):
            raise UserError('concat: parts must be a list of encoder configs, e.g. [{"name": "patch-pixels"}, '
                            '{"name": "task-cnn", "ckpt": DIR}]')
        if any(p["name"] == self.name for p in parts):
            raise UserError("concat: a part may not itself be a concat; list its parts instead")
        scales = [1.0] * len(parts) if scales is None else list(scales)
        if len(scales) != len(parts) or not all(isinstance(s, (int, float)) and not isinstance(s, bool) and s > 0
                                                for s in scales):
            raise UserError(f"concat: scales must be one positive number per part ({len(parts)}), got {scales}")
        built = [make_encoder(p["name"], **{k: v for k, v in p.items() if k != "name"}) for p in parts]
        grids = {e.num_patches for e in built}
        if len(grids) > 1:
            raise UserError(f"concat: the parts give {', '.join(str(e.num_patches) for e in built)} tokens an "
                            f"image; side by side they need the same grid (e.g. patch-pixels with patch_size 16 "
                            f"at 64 px and task-cnn both give 16)")
        super().__init__(max(e.input_size for e in built))
        self.parts = torch.nn.ModuleList(built)
        self.scales = [float(s) for s in scales]

    @property
    def num_patches(self) -> int:
        return self.parts[0].num_patches

    @property
    def dim(self) -> int:
        return sum(e.dim for e in self.parts)

    def encode(self, images: torch.Tensor | Any, return_cls: bool = False
               ) -> torch.Tensor | tuple[torch.Tensor, None]:
        """uint8 images (B, H, W, 3) -> tokens (B, N, sum D) float32; each part encodes the images itself."""
        z = torch.cat([e.encode(images) * s for e, s in zip(self.parts, self.scales)], dim=-1)  # (B, N, sum D)
        return (z, None) if return_cls else z

    def part_tokens(self, z: torch.Tensor, i: int) -> torch.Tensor:
        """Part ``i``'s own tokens from concat tokens (..., sum D) -> (..., D_i), its scale undone (e.g. to draw a
        concat model's predictions with a decoder of that part's encoder)."""
        if not 0 <= i < len(self.parts):
            raise UserError(f"concat: part {i} asked for, it has {len(self.parts)} parts (0-{len(self.parts) - 1})")
        start = sum(e.dim for e in self.parts[:i])
        return z[..., start:start + self.parts[i].dim] / self.scales[i]

    def config_dict(self) -> dict[str, Any]:
        """The parts' configs without their weights' local ``path`` (as ``wm train`` records any encoder)."""
        parts = [{k: v for k, v in e.config_dict().items() if k != "path"} for e in self.parts]
        return {"name": self.name, "parts": parts, "scales": self.scales}
