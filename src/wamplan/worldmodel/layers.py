"""Transformer pieces shared by the predictor and the decoder: pre-norm blocks whose attention takes
an optional rotary embedding, a boolean mask, and cached keys/values of earlier frames.

Notation: B batch, L query tokens, S key tokens, h heads, e head dim, d model width.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

KV = tuple[torch.Tensor, torch.Tensor]  # (k, v), each (B or 1, h, M, e)


def rope_angles(positions: torch.Tensor, inv_freq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """positions (L,) float, inv_freq (e/2,) -> cos, sin each (L, e) for ``apply_rope``."""
    ang = positions.float()[:, None] * inv_freq.float()[None, :]  # (L, e/2), float32 whatever the model dtype
    ang = torch.cat([ang, ang], dim=-1)  # (L, e)
    return ang.cos(), ang.sin()


def apply_rope(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotate pairs (i, i + e/2) of x (B, h, L, e) by the angles in cos/sin (L, e)."""
    cos, sin = cos.to(x.dtype), sin.to(x.dtype)
    x1, x2 = x.chunk(2, dim=-1)  # (B, h, L, e/2) each
    return x * cos + torch.cat([-x2, x1], dim=-1) * sin  # (B, h, L, e)


class KVRing:
    """One layer's keys/values for an inference rollout, preallocated for ``frames`` frames (H_ctx).

    Each step writes the new frame's (k, v) into a slot, overwriting the frame that left the window, and
    attends over the filled slots. Without a mask the key order does not matter (softmax over a set, RoPE
    already applied), so nothing is shifted or concatenated. In-place writes: inference only (no autograd).
    """

    def __init__(self, frames: int, prefix: list[KV]) -> None:
        self.frames, self.prefix = frames, prefix
        self.k: torch.Tensor | None = None  # (B, h, frames M, e)
        self.v: torch.Tensor | None = None

    def write_and_read(self, k: torch.Tensor, v: torch.Tensor, slot: int, valid: int) -> KV:
        """Store k, v (B, h, M, e) in ``slot``; return the keys/values of the first ``valid`` slots."""
        b, h, m, e = k.shape
        if self.k is None or self.v is None:  # first step: allocate, copy the (broadcast) prefix once
            self.k, self.v = k.new_empty(b, h, self.frames * m, e), v.new_empty(b, h, self.frames * m, e)
            for i, (pk, pv) in enumerate(self.prefix):
                self.k[:, :, i * m:(i + 1) * m] = pk
                self.v[:, :, i * m:(i + 1) * m] = pv
        self.k[:, :, slot * m:(slot + 1) * m] = k
        self.v[:, :, slot * m:(slot + 1) * m] = v
        return self.k[:, :, :valid * m], self.v[:, :, :valid * m]  # (B, h, valid M, e) each


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int, head_dim: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.heads, self.head_dim = heads, head_dim
        self.qkv = nn.Linear(dim, 3 * heads * head_dim)
        self.proj = nn.Linear(heads * head_dim, dim)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor] | None = None,
                mask: torch.Tensor | None = None, past: list[KV] | None = None,
                ring: tuple[KVRing, int, int] | None = None) -> tuple[torch.Tensor, KV]:
        """x (B, L, d); rope cos/sin (L, e); mask (L, S) bool, True = may attend; past: cached (k, v)
        of earlier frames, each (B or 1, h, M, e), prepended to this call's keys (expanded to B);
        or ring = (KVRing, slot, valid) instead of past (inference).
        Returns the output (B, L, d) and this call's own (k, v), each (B, h, L, e), for a cache."""
        b, n, _ = x.shape
        qkv = self.qkv(x).view(b, n, 3, self.heads, self.head_dim).permute(2, 0, 3, 1, 4)  # (3, B, h, L, e)
        q, k, v = qkv.unbind(0)  # (B, h, L, e) each
        if rope is not None:
            q, k = apply_rope(q, *rope), apply_rope(k, *rope)
        own = (k, v)
        if ring is not None:
            k, v = ring[0].write_and_read(k, v, ring[1], ring[2])  # (B, h, S, e)
        elif past:
            k = torch.cat([pk.expand(b, -1, -1, -1) for pk, _ in past] + [k], dim=2)  # (B, h, S, e)
            v = torch.cat([pv.expand(b, -1, -1, -1) for _, pv in past] + [v], dim=2)  # (B, h, S, e)
        o = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)  # (B, h, L, e)
        o = o.transpose(1, 2).reshape(b, n, self.heads * self.head_dim)  # (B, L, h e)
        return self.drop(self.proj(o)), own


class Block(nn.Module):
    """Pre-norm transformer block: x + attn(ln(x)), then x + mlp(ln(x))."""

    def __init__(self, dim: int, heads: int, head_dim: int, mlp_dim: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads, head_dim, dropout)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, mlp_dim), nn.GELU(), nn.Linear(mlp_dim, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor] | None = None,
                mask: torch.Tensor | None = None, past: list[KV] | None = None,
                ring: tuple[KVRing, int, int] | None = None) -> tuple[torch.Tensor, KV]:
        a, kv = self.attn(self.norm1(x), rope, mask, past, ring)  # (B, L, d)
        x = x + a
        return x + self.mlp(self.norm2(x)), kv  # (B, L, d)


class AdaLNBlock(Block):
    """A :class:`Block` whose two branches a per-frame condition c modulates (adaLN-Zero, DiT):
    x + g1 * attn(ln(x) * (1 + s1) + b1), then x + g2 * mlp(ln(x) * (1 + s2) + b2), with (b, s, g) from one
    linear map of c. ``zero_init`` zeroes that map, so the block starts as the identity (DiT's adaLN-Zero)."""

    def __init__(self, dim: int, heads: int, head_dim: int, mlp_dim: int, cond_dim: int, dropout: float = 0.0) -> None:
        super().__init__(dim, heads, head_dim, mlp_dim, dropout)
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 6 * dim))

    def zero_init(self) -> None:
        nn.init.zeros_(self.ada[-1].weight)
        nn.init.zeros_(self.ada[-1].bias)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor] | None = None,
                mask: torch.Tensor | None = None, past: list[KV] | None = None,
                ring: tuple[KVRing, int, int] | None = None, cond: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, KV]:
        """x (B, T M', d): T frames of M' tokens each; cond (B or 1, T, C), one condition per frame."""
        if cond is None:
            raise ValueError("AdaLNBlock needs cond (B, T, C): the per-frame condition")
        b, n, d = x.shape
        t = cond.shape[1]
        b1, s1, g1, b2, s2, g2 = self.ada(cond)[:, :, None].chunk(6, dim=-1)  # (B or 1, T, 1, d) each

        def frames(h: torch.Tensor) -> torch.Tensor:  # (B, T M', d) -> (B, T, M', d)
            return h.view(b, t, n // t, d)

        a, kv = self.attn((frames(self.norm1(x)) * (1 + s1) + b1).view(b, n, d), rope, mask, past, ring)
        x = x + (frames(a) * g1).view(b, n, d)  # (B, T M', d)
        h = self.mlp((frames(self.norm2(x)) * (1 + s2) + b2).view(b, n, d))  # (B, T M', d)
        return x + (frames(h) * g2).view(b, n, d), kv


def init_weights(module: nn.Module) -> None:
    """ViT-style init: truncated normal(0.02) linears, zero biases, unit LayerNorms."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.trunc_normal_(m.weight, std=0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.LayerNorm):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
