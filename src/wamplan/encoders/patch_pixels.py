"""``patch-pixels``: the CPU default encoder. No weights, no download, a few microseconds an image.

Each image is resized to ``input_size`` px, normalised with the ImageNet mean/std, and cut into
non-overlapping ``patch_size`` x ``patch_size`` patches; a token is the patch's raw pixels
(D = 3 * patch_size**2), optionally followed by a FIXED orthogonal projection to ``proj_dim``:

- ``basis="random"`` (default): a random one (seeded, generated with numpy's frozen ``RandomState`` so every
  machine builds the same matrix), a Johnson-Lindenstrauss sketch that keeps every spatial frequency alike;
- ``basis="dct"``: the patch's ``proj_dim`` lowest-frequency 2-D DCT-II coefficients in all (frequencies
  ordered by u + v, then u, each in R, G and B before the next: 128 of a 16-px patch are 42 frequencies in
  all three colours and a 43rd in two), a low-pass within each patch: a sub-patch shift of a smooth edge
  moves these coefficients smoothly, while the finest detail, whose change under a shift is the hardest to
  predict, is dropped. ``seed`` plays no part.

What it costs in quality, honestly: the tokens carry no semantics. Two images are close only if their
downsampled pixels are close, so the world model's planning cost (eq. 3 of the paper) becomes a pixel
MSE between downsampled images (or a Johnson-Lindenstrauss sketch of it when projected): it sees
colour and position of large blobs (arm, cube) but not fine contact geometry, is sensitive to
lighting, and rewards matching the background as much as the object. DINOv3 features are invariant
to much of that and separate "cube in hole" from "cube on rim" far better. Use this encoder to make
the pipeline run on a CPU, not to reproduce the paper's numbers.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from wamplan.encoders.base import FrozenEncoder, register_encoder
from wamplan.errors import UserError


def orthogonal_projection(in_dim: int, out_dim: int, seed: int) -> torch.Tensor:
    """(in_dim, out_dim) matrix with orthonormal columns, the same on every machine for a seed.

    A random orthonormal projection keeps out_dim/in_dim of a vector's squared norm in expectation, so
    the mean squared value *per element* is preserved: MSEs in the projected space are comparable
    with MSEs on raw pixels.
    """
    g = np.random.RandomState(seed).standard_normal((in_dim, out_dim))  # (in, out) float64
    q, r = np.linalg.qr(g)  # q (in, out) orthonormal columns
    q = q * np.sign(np.diag(r))[None, :]  # fix the sign ambiguity of QR: unique for a given g
    return torch.from_numpy(q).float()


def dct_projection(patch_size: int, out_dim: int) -> torch.Tensor:
    """(3 p p, out_dim) matrix whose columns are orthonormal 2-D DCT-II basis images of one colour channel,
    the lowest frequencies first: ordered by u + v, then u, then the channel (R, G, B), so every
    frequency kept is kept in all three channels before a higher one. Columns index the flattened
    (3, p, p) patch, the token layout of :class:`PatchPixelEncoder`."""
    p = patch_size
    n = np.arange(p)
    c = np.cos(np.pi * (n[None, :] + 0.5) * n[:, None] / p)  # (u, x): 1-D DCT-II rows
    c *= np.sqrt(2.0 / p)
    c[0] /= np.sqrt(2.0)  # orthonormal rows
    freqs = sorted(((u, v) for u in range(p) for v in range(p)), key=lambda f: (f[0] + f[1], f[0]))
    cols = []
    for u, v in freqs:
        img = np.outer(c[u], c[v])  # (p, p) basis image, frequency u along y, v along x
        for ch in range(3):
            col = np.zeros((3, p, p))
            col[ch] = img
            cols.append(col.reshape(-1))
            if len(cols) == out_dim:
                return torch.from_numpy(np.stack(cols, axis=1)).float()  # (3 p p, out_dim)
    raise ValueError(f"out_dim {out_dim} exceeds 3 * patch_size**2 = {3 * p * p}")


BASES = ("random", "dct")


@register_encoder("patch-pixels")
class PatchPixelEncoder(FrozenEncoder):
    """Raw normalised pixels of a patch grid, optionally projected (random or DCT basis). See the module doc."""

    name = "patch-pixels"

    def __init__(self, input_size: int = 64, patch_size: int = 16, proj_dim: int | None = 128,
                 seed: int = 0, basis: str = "random") -> None:
        for key, value in (("input_size", input_size), ("patch_size", patch_size), ("seed", seed),
                           ("proj_dim", 1 if proj_dim is None else proj_dim)):
            if not isinstance(value, int) or isinstance(value, bool):
                raise UserError(f"patch-pixels: {key} must be a whole number{' or None' if key == 'proj_dim' else ''}, "
                                f"got {value!r}")
        if patch_size <= 0:
            raise UserError(f"patch-pixels: patch_size must be > 0, got {patch_size}")
        super().__init__(input_size)
        if basis not in BASES:
            raise UserError(f"patch-pixels: basis must be one of {', '.join(BASES)}, got {basis!r}")
        if basis == "dct" and proj_dim is None:
            raise UserError("patch-pixels: basis 'dct' keeps proj_dim coefficients; give proj_dim (e.g. 128), "
                            "or drop basis for raw pixels")
        if input_size % patch_size:
            raise UserError(f"patch-pixels: input_size {input_size} is not a multiple of patch_size "
                            f"{patch_size}; pick sizes that divide")
        raw = 3 * patch_size * patch_size
        if proj_dim is not None and not 0 < proj_dim <= raw:
            raise UserError(f"patch-pixels: proj_dim must be in 1..{raw} (3 * patch_size**2) or None, "
                            f"got {proj_dim}")
        self.patch_size = patch_size
        self.grid = input_size // patch_size
        self.proj_dim = proj_dim
        self.seed = seed
        self.basis = basis
        self._raw_dim = raw
        if proj_dim is None:
            proj = torch.empty(0)
        elif basis == "dct":
            proj = dct_projection(patch_size, proj_dim)
        else:
            proj = orthogonal_projection(raw, proj_dim, seed)
        self.register_buffer("proj", proj, persistent=False)  # (3 p p, proj_dim) or empty

    @property
    def num_patches(self) -> int:
        return self.grid * self.grid

    @property
    def dim(self) -> int:
        return self.proj_dim if self.proj_dim is not None else self._raw_dim

    def _features(self, pixels: torch.Tensor) -> tuple[torch.Tensor, None]:
        b, p, g = pixels.shape[0], self.patch_size, self.grid
        x = pixels.view(b, 3, g, p, g, p).permute(0, 2, 4, 1, 3, 5)  # (B, gy, gx, 3, p, p)
        x = x.reshape(b, g * g, 3 * p * p)  # (B, N, 3 p p), row-major patch order
        if self.proj_dim is not None:
            x = x @ self.proj  # (B, N, proj_dim)
        return x, None

    def config_dict(self) -> dict[str, Any]:
        cfg = {"name": self.name, "input_size": self.input_size, "patch_size": self.patch_size,
               "proj_dim": self.proj_dim, "seed": self.seed}
        if self.basis != "random":  # the default stays out, so existing feature caches keep their key
            cfg["basis"] = self.basis
        return cfg
