"""The latent predictor f_theta (paper §3.2): a block-causal ViT over frozen patch tokens.

A frame t is its visual tokens z_t (V, N, D), its proprioception q_t (P,) and its action block
a_t (Delta*A,): the Delta actions executed from frame t, flattened time-major (``action_blocks``).
q_t and a_t go through their own MLP projectors and are concatenated to every visual token of frame t;
one linear maps the concatenation to the model width, and a learned spatial embedding per
(view, patch) is added. The output at frame t predicts frame t+1 (Delta control steps later): tokens
(V, N, D) and proprioception (P,) (by default as a change from frame t: ``predict_delta``).

Variants (``PredictorConfig``; the defaults are the model above, which the shipped checkpoints are):

* ``action_conditioning="adaln"``: every block is an :class:`~wamplan.worldmodel.layers.AdaLNBlock`, its
  attention and MLP branches shifted, scaled and gated per frame by a linear map of the frame's action
  embedding proj(a_t) (zero-initialised: DiT's adaLN-Zero). The input path above stays.
* ``action_tokens=True``: each frame also carries Delta tokens, one per control step of its action block
  (MLP(a_{t,k}) + a learned step embedding), so M' = M + Delta tokens a frame run through the blocks; only
  the M visual tokens are read out.
* ``predict_delta`` (readout as a change) and the width/depth fields. Both variants keep a frame's keys and
  values a function of that frame's own inputs and the frames before it, so the KV cache below holds for all.

Planning use (one chunk; context frames t-2, t-1 and the current frame t, candidates a (C, S, Delta*A)):

    prefix = wm.encode_prefix(z[:, :2], q[:, :2], a_past)   # (1, 2, ...): once per chunk, batch 1
    for it in range(iterations):                             # CEM iterations reuse the prefix
        z_pred, q_pred = wm.rollout_from_prefix(prefix, z[:, 2], q[:, 2], a)   # (C, S, V, N, D), (C, S, P)
        cost = (z_pred[:, -1] - z_target).pow(2).flatten(1).mean(1)          # (C,), paper eq. 3

Time. Tokens of frame t attend to every token of frames t-H_ctx+1 .. t and to nothing later (a sliding
window, block-causal). Time enters only through a rotary embedding of the frame index on queries and
keys, so attention scores depend on frame *distance* and there is no absolute frame-slot embedding.
Hence a frame's keys/values never change once computed, and a rollout keeps a KV cache: each step runs
only the new frame's M = V*N tokens against the cached keys/values of the previous H_ctx-1 frames.
Context frames shared by all candidates are computed once with batch 1 (``encode_prefix``) and
broadcast to the B candidates, and the same prefix serves every CEM iteration of a chunk.

Semantics (a deliberate difference from DINO-WM). The sequence starts at the first context frame and
every frame attends to its own H_ctx window; with depth > 1 the receptive field therefore grows
(a frame's keys carry information from up to depth*(H_ctx-1) frames back). DINO-WM instead re-encodes
the last H_ctx frames from scratch every step, so a frame's features change with its window slot and
nothing can be cached. ``rollout(..., naive=True)`` re-runs ``forward`` over the whole sequence so far
each step: the reference the cached path must equal (tests assert it). Training unrolls with the same
``rollout``, so training and planning see the same computation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from wamplan.envs.spec import DEFAULT_TASK, TaskSpec, get_task
from wamplan.errors import UserError
from wamplan.worldmodel.config import PredictorConfig, predictor_config
from wamplan.worldmodel.layers import KV, AdaLNBlock, Block, KVRing, init_weights, rope_angles


def action_blocks(actions: torch.Tensor, frameskip: int) -> torch.Tensor:
    """Per-step actions (..., S*Delta, A) -> frame action blocks (..., S, Delta*A), time-major:
    block s is [a_{s Delta}, a_{s Delta + 1}, ...] flattened. The one layout for datasets and planners."""
    *lead, steps, dim = actions.shape
    if steps % frameskip:
        raise ValueError(f"{steps} actions do not split into blocks of frameskip {frameskip}")
    return actions.reshape(*lead, steps // frameskip, frameskip * dim)


# Modules that older checkpoints hold and this version no longer builds: the spread head's and the state head's
# (removed: no measured gain; :data:`~wamplan.worldmodel.config.RETIRED_PREDICTOR_KEYS` are their config keys).
RETIRED_MODULES = ("spread_head", "state_head")


def without_retired(weights: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A checkpoint's weights without those of :data:`RETIRED_MODULES`, at any depth."""
    return {k: v for k, v in weights.items() if not set(k.split(".")) & set(RETIRED_MODULES)}


@dataclass
class PrefixCache:
    """Keys/values of context frames, to be extended by ``rollout_from_prefix``.

    ``frames[i][l]`` is the (k, v) of the i-th kept frame at layer l, each (Bp, heads, M, head_dim), where
    Bp is 1 for a prefix shared by all candidates. ``start`` is the sequence index of the next frame.
    """

    frames: list[list[KV]]
    start: int

    @property
    def batch(self) -> int:
        return self.frames[0][0][0].shape[0] if self.frames else 1


class WorldModelPredictor(nn.Module):
    """The predictor of ``cfg``. ``task`` (a :class:`~wamplan.envs.spec.TaskSpec`; None: not known, e.g. a model
    built in memory) and ``cameras`` (the camera of each of the V views, in order) say what it was trained on;
    a checkpoint records both and ``worldmodel.load.load_predictor`` always sets ``task``."""

    def __init__(self, cfg: PredictorConfig, task: str | TaskSpec | None = None,
                 cameras: Sequence[str] | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.task = get_task(task) if task is not None else None
        if cameras is not None and len(cameras) != cfg.num_views:
            raise UserError(f"the predictor has {cfg.num_views} views but {len(cameras)} cameras {list(cameras)} "
                            f"were given; pass one camera per view")
        self._cameras = tuple(cameras) if cameras is not None else None
        d, e = cfg.width, cfg.head_dim
        self.proprio_proj = nn.Sequential(nn.Linear(cfg.proprio_dim, cfg.proprio_emb), nn.GELU(),
                                          nn.Linear(cfg.proprio_emb, cfg.proprio_emb))
        self.action_proj = nn.Sequential(nn.Linear(cfg.action_block_dim, cfg.action_emb), nn.GELU(),
                                         nn.Linear(cfg.action_emb, cfg.action_emb))
        self.in_proj = nn.Linear(cfg.enc_dim + cfg.proprio_emb + cfg.action_emb, d)  # over [z, q_emb, a_emb]
        self.pos = nn.Parameter(torch.zeros(cfg.tokens_per_frame, d))  # (M, d), one per (view, patch)
        self.blocks = nn.ModuleList(self._block() for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(d)
        self.z_head = nn.Linear(d, cfg.enc_dim)
        self.q_head = nn.Linear(d, cfg.proprio_dim)
        # Per-dim feature statistics (set from the training set by the trainer; saved in checkpoints).
        self.register_buffer("z_mean", torch.zeros(cfg.enc_dim))  # (D,)
        self.register_buffer("z_std", torch.ones(cfg.enc_dim))  # (D,)
        inv_freq = cfg.rope_base ** -(torch.arange(0, e, 2, dtype=torch.float32) / e)  # (e/2,) 1 .. base^-1
        self.register_buffer("inv_freq", inv_freq, persistent=False)
        if cfg.action_tokens:  # one token per control step of the action block
            self.action_token = nn.Sequential(nn.Linear(cfg.action_dim, d), nn.GELU(), nn.Linear(d, d))
            self.action_pos = nn.Parameter(torch.zeros(cfg.frameskip, d))  # (Delta, d), one per step of the block
        init_weights(self)
        nn.init.trunc_normal_(self.pos, std=0.02)
        if cfg.action_tokens:
            nn.init.trunc_normal_(self.action_pos, std=0.02)
        for blk in self.blocks:
            if isinstance(blk, AdaLNBlock):
                blk.zero_init()  # adaLN-Zero: every block starts as the identity
        # The heads keep the small random init: zero-initialised delta heads (an exact copy-last start)
        # made training stall on a plateau in 3 of 4 seeds on the synthetic task.

    @classmethod
    def from_record(cls, saved: dict[str, Any]) -> "WorldModelPredictor":
        """An untrained predictor as a checkpoint's config record describes it: its ``predictor`` config, and the
        task and cameras of its ``data`` (a record without a task: the cube-insertion task's)."""
        trained_on = saved.get("data") or {}
        return cls(predictor_config(saved["predictor"]), trained_on.get("task") or DEFAULT_TASK,
                   trained_on.get("cameras"))

    @property
    def cameras(self) -> tuple[str, ...] | None:
        """The camera of each of the V views, in order: the recorded ones, else the task's when it has V cameras
        (a checkpoint made before tasks: the cube's three), else None."""
        if self._cameras is not None:
            return self._cameras
        if self.task is not None and len(self.task.cameras) == self.cfg.num_views:
            return self.task.cameras
        return None

    def _block(self) -> Block:
        cfg = self.cfg
        if cfg.action_conditioning == "adaln":
            return AdaLNBlock(cfg.width, cfg.heads, cfg.head_dim, cfg.mlp_dim, cfg.action_emb, cfg.dropout)
        return Block(cfg.width, cfg.heads, cfg.head_dim, cfg.mlp_dim, cfg.dropout)

    # -- pieces --------------------------------------------------------------------------------------
    def set_feature_stats(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Per-dim mean/std (D,) of the visual features, used to normalise inputs and scale outputs."""
        self.z_mean.copy_(mean.to(self.z_mean))
        self.z_std.copy_(std.to(self.z_std).clamp_min(1e-4))

    def _embed(self, z: torch.Tensor, q: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """z (Bz, T, V, N, D), q (Bq, T, P), a (Ba, T, Delta*A) -> tokens (B, T, M', d), B = max batch, and the
        blocks' per-frame condition: the action embedding (Ba, T, Ea) with ``action_conditioning="adaln"``, else
        None. M' = M visual tokens, then (``action_tokens``) Delta action tokens.

        in_proj(concat(z, proj(q), proj(a))) is computed block by block (same linear map), so a visual
        part with batch 1 is broadcast against per-candidate actions without being copied.
        """
        cfg = self.cfg
        w, b = self.in_proj.weight, self.in_proj.bias  # (d, D + Eq + Ea), (d,)
        i_q, i_a = cfg.enc_dim, cfg.enc_dim + cfg.proprio_emb
        dt = w.dtype
        zn = (z.to(dt) - self.z_mean) / self.z_std  # (Bz, T, V, N, D)
        xz = F.linear(zn.flatten(2, 3), w[:, :i_q])  # (Bz, T, M, d)
        xq = F.linear(self.proprio_proj(q.to(dt)), w[:, i_q:i_a])  # (Bq, T, d)
        a_emb = self.action_proj(a.to(dt))  # (Ba, T, Ea)
        xa = F.linear(a_emb, w[:, i_a:], b)  # (Ba, T, d)
        x = xz + (xq + xa)[:, :, None] + self.pos  # (B, T, M, d)
        if cfg.action_tokens:
            steps = a.to(dt).unflatten(-1, (cfg.frameskip, cfg.action_dim))  # (Ba, T, Delta, A)
            xt = self.action_token(steps) + self.action_pos  # (Ba, T, Delta, d)
            x = torch.cat([x, xt.expand(x.shape[0], -1, -1, -1)], dim=2)  # (B, T, M + Delta, d)
        return x, (a_emb if cfg.action_conditioning == "adaln" else None)

    def _blocks(self, x: torch.Tensor, t0: int, past: list[list[KV]],
                ring: tuple[list[KVRing], int, int] | None = None,
                cond: torch.Tensor | None = None) -> tuple[torch.Tensor, list[KV]]:
        """Run frames t0 .. t0+T-1 (x (B, T, M, d), M tokens a frame) attending to ``past`` frames
        t0-len(past) .. t0-1 and to each other, within the H_ctx window. Returns hidden (B, T, M, d) and
        per-layer (k, v) of the new frames, each (B, heads, T*M, e). ``ring`` = (per-layer KVRing, slot,
        valid frames) replaces ``past`` for one-frame inference steps. ``cond`` (B or 1, T, Ea): the frames'
        condition for adaLN blocks (None for plain blocks)."""
        b, t, m, d = x.shape
        n_past = len(past) if ring is None else ring[2] - 1
        fq = torch.arange(t0, t0 + t, device=x.device)  # (T,) query frame indices
        mask = None  # one new frame with at most H_ctx-1 cached ones: every key is visible
        if t > 1 or n_past + t > self.cfg.context:
            fk = torch.arange(t0 - n_past, t0 + t, device=x.device)  # (P + T,) key frame indices
            dist = fq[:, None] - fk[None, :]  # (T, P + T)
            allowed = (dist >= 0) & (dist < self.cfg.context)  # (T, P + T) block-causal window
            mask = allowed.repeat_interleave(m, 0).repeat_interleave(m, 1)  # (T M, (P + T) M), True = attend
        rope = rope_angles(fq.repeat_interleave(m).float(), self.inv_freq)  # cos, sin (T M, e)
        h = x.reshape(b, t * m, d)  # (B, T M, d)
        extra = {} if cond is None else {"cond": cond}
        kvs = []
        for layer, blk in enumerate(self.blocks):
            if ring is not None:
                h, kv = blk(h, rope, None, None, (ring[0][layer], ring[1], ring[2]), **extra)
            else:
                h, kv = blk(h, rope, mask, [frame[layer] for frame in past], **extra)
            kvs.append(kv)
        return h.view(b, t, m, d), kvs

    def _visual(self, h: torch.Tensor) -> torch.Tensor:
        """hidden (B, T, M', d) -> the M visual tokens' normed hidden (B, T, M, d), what every head reads (action
        tokens are not read out)."""
        return self.norm(h[:, :, :self.cfg.tokens_per_frame])

    def _readout(self, hn: torch.Tensor, z: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """normed visual hidden (B, T, M, d) (:meth:`_visual`) and the inputs z (Bz, T, V, N, D), q (Bq, T, P) of
        the same frames -> next-frame predictions z (B, T, V, N, D), q (B, T, P)."""
        cfg = self.cfg
        dz = self.z_head(hn).unflatten(2, (cfg.num_views, cfg.num_patches)) * self.z_std  # (B, T, V, N, D)
        dq = self.q_head(hn.mean(dim=2))  # (B, T, P), pooled over the frame's tokens
        if cfg.predict_delta:
            return z.to(dz.dtype) + dz, q.to(dq.dtype) + dq
        return dz + self.z_mean, dq

    def _check(self, z: torch.Tensor, q: torch.Tensor, a: torch.Tensor, frames: int | None = None) -> None:
        cfg = self.cfg
        want_z = (cfg.num_views, cfg.num_patches, cfg.enc_dim)
        if z.ndim != 5 or tuple(z.shape[2:]) != want_z:
            raise ValueError(f"z must be (B, T, {', '.join(map(str, want_z))}), got {tuple(z.shape)}")
        if q.ndim != 3 or q.shape[-1] != cfg.proprio_dim:
            raise ValueError(f"q must be (B, T, {cfg.proprio_dim}), got {tuple(q.shape)}")
        if a.ndim != 3 or a.shape[-1] != cfg.action_block_dim:
            raise ValueError(f"a must be (B, T, {cfg.action_block_dim}) (Delta*A), got {tuple(a.shape)}")
        t = frames if frames is not None else z.shape[1]
        if not z.shape[1] == q.shape[1] == t or a.shape[1] != t:
            raise ValueError(f"z, q, a must hold {t} frames; got {z.shape[1]}, {q.shape[1]}, {a.shape[1]}")

    # -- public API ----------------------------------------------------------------------------------
    def normalised(self, z: torch.Tensor) -> torch.Tensor:
        """Latents z (..., D) in the units the predictor reads them: per-dim standardised by the feature stats."""
        return (z.to(self.z_mean.dtype) - self.z_mean) / self.z_std

    def forward(self, z: torch.Tensor, q: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Teacher-forced: z (B, T, V, N, D), q (B, T, P), a (B, T, Delta*A) -> predictions of frames
        1..T: z (B, T, V, N, D), q (B, T, P) (output t is the prediction of frame t+1)."""
        self._check(z, q, a)
        x, cond = self._embed(z, q, a)  # (B, T, M', d), (B, T, Ea) or None
        h, _ = self._blocks(x, 0, [], cond=cond)  # (B, T, M', d)
        return self._readout(self._visual(h), z, q)

    def encode_prefix(self, z: torch.Tensor, q: torch.Tensor, a: torch.Tensor) -> PrefixCache:
        """Cache the context frames before the current one: z (Bp, Tp, V, N, D), q (Bp, Tp, P),
        a (Bp, Tp, Delta*A) (a[:, i] executed from frame i). Bp = 1 to share them among candidates.
        Reuse the result for every CEM iteration of a chunk (it is never modified)."""
        self._check(z, q, a)
        tp, m = z.shape[1], self.cfg.frame_tokens
        keep = self.cfg.context - 1
        if tp == 0 or keep == 0:
            return PrefixCache([], tp)
        x, cond = self._embed(z, q, a)  # (Bp, Tp, M', d), (Bp, Tp, Ea) or None
        _, kvs = self._blocks(x, 0, [], cond=cond)  # per layer (Bp, heads, Tp M', e)
        frames = [[(k[:, :, i * m:(i + 1) * m], v[:, :, i * m:(i + 1) * m]) for k, v in kvs]
                  for i in range(max(0, tp - keep), tp)]
        return PrefixCache(frames, tp)

    def rollout_from_prefix(self, prefix: PrefixCache, z_cur: torch.Tensor, q_cur: torch.Tensor,
                            a_future: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """KV-cached autoregressive rollout. z_cur (Bc, V, N, D), q_cur (Bc, P): the current frame (Bc = 1
        or B); a_future (B, S, Delta*A): a_future[:, 0] is executed from the current frame.
        Returns predicted frames 1..S after the current one: z (B, S, V, N, D), q (B, S, P)."""
        self._check(z_cur[:, None], q_cur[:, None], a_future[:, :1], frames=1)
        h_ctx, keep = self.cfg.context, self.cfg.context - 1
        window, t = list(prefix.frames), prefix.start
        # Without autograd, keys/values live in preallocated per-layer rings (no per-step concatenation).
        rings = None
        if keep > 0 and not torch.is_grad_enabled():
            rings = [KVRing(h_ctx, [frame[layer] for frame in window]) for layer in range(len(self.blocks))]
        z_t, q_t = z_cur[:, None], q_cur[:, None]  # (Bc, 1, V, N, D), (Bc, 1, P)
        zs, qs = [], []
        for s in range(a_future.shape[1]):
            x, cond = self._embed(z_t, q_t, a_future[:, s:s + 1])  # (B, 1, M', d), (B, 1, Ea) or None
            if rings is not None:
                n = len(window) + s  # frames already in the rings' history
                h, _ = self._blocks(x, t, [], (rings, n % h_ctx, min(n + 1, h_ctx)), cond)  # (B, 1, M', d)
            else:
                h, kv = self._blocks(x, t, window, cond=cond)  # (B, 1, M', d); per layer (B, heads, M', e)
                window = (window + [kv])[-keep:] if keep > 0 else []  # the last H_ctx-1 frames
            z_t, q_t = self._readout(self._visual(h), z_t, q_t)  # (B, 1, V, N, D), (B, 1, P)
            zs.append(z_t)
            qs.append(q_t)
            t += 1
        return torch.cat(zs, dim=1), torch.cat(qs, dim=1)  # (B, S, V, N, D), (B, S, P)

    def rollout(self, z_ctx: torch.Tensor, q_ctx: torch.Tensor, a_ctx_past: torch.Tensor,
                a_future: torch.Tensor, naive: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Autoregressive S-step prediction from context frames.

        z_ctx (Bc, Tc, V, N, D), q_ctx (Bc, Tc, P): context frames, the last is the current one (Tc is
        usually H_ctx); a_ctx_past (Bc, Tc-1, Delta*A): actions executed from the earlier context frames;
        a_future (B, S, Delta*A): candidate action blocks, a_future[:, 0] executed from the current frame.
        Bc is 1 (context shared by all B candidates, computed once) or B.
        Returns z (B, S, V, N, D), q (B, S, P): predictions Delta, 2 Delta, ..., S Delta steps ahead.
        ``naive=True`` re-runs ``forward`` over the whole sequence every step (slow reference).
        """
        if naive:
            return self._rollout_naive(z_ctx, q_ctx, a_ctx_past, a_future)
        prefix = self.encode_prefix(z_ctx[:, :-1], q_ctx[:, :-1], a_ctx_past)
        return self.rollout_from_prefix(prefix, z_ctx[:, -1], q_ctx[:, -1], a_future)

    def _rollout_naive(self, z_ctx: torch.Tensor, q_ctx: torch.Tensor, a_ctx_past: torch.Tensor,
                       a_future: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = max(z_ctx.shape[0], a_future.shape[0])
        dt = self.in_proj.weight.dtype
        zs = z_ctx.to(dt).expand(b, -1, -1, -1, -1)  # (B, Tc, V, N, D)
        qs = q_ctx.to(dt).expand(b, -1, -1)  # (B, Tc, P)
        acts = torch.cat([a_ctx_past.expand(b, -1, -1), a_future[:, :1].expand(b, -1, -1)], dim=1)  # (B, Tc, DA)
        out_z, out_q = [], []
        for s in range(a_future.shape[1]):
            zp, qp = self.forward(zs, qs, acts)  # (B, T, V, N, D), (B, T, P)
            out_z.append(zp[:, -1:])
            out_q.append(qp[:, -1:])
            zs, qs = torch.cat([zs, zp[:, -1:]], dim=1), torch.cat([qs, qp[:, -1:]], dim=1)
            if s + 1 < a_future.shape[1]:
                acts = torch.cat([acts, a_future[:, s + 1:s + 2].expand(b, -1, -1)], dim=1)
        return torch.cat(out_z, dim=1), torch.cat(out_q, dim=1)  # (B, S, V, N, D), (B, S, P)

    def compile_blocks(self, backend: Any = "inductor") -> "WorldModelPredictor":
        """Compile every transformer block with ``torch.compile`` (``backend``; dynamic shapes: the key length
        grows through a rollout). The first calls compile; the outputs are those of the eager blocks up to
        floating-point reordering. Returns self."""
        for blk in self.blocks:
            blk.compile(dynamic=True, backend=backend)
        return self

    def _apply(self, fn, recurse: bool = True):
        """``nn.Module``'s device and dtype casts, except that the rotary frequencies stay float32 (a model cast
        to bfloat16 would otherwise round them before the angles are computed)."""
        freqs = self.inv_freq  # (e/2,) float32
        super()._apply(fn, recurse)
        self.inv_freq = freqs.to(self.inv_freq.device)  # the cast's device, float32 values unrounded
        return self

    def num_params(self) -> int:
        return sum(p.numel() for p in self.parameters())
