"""``patch-pixels``: the CPU default encoder. No weights, no download, a few microseconds an image.

Each image is resized to ``input_size`` px, normalised with the ImageNet mean/std, and cut into
non-overlapping ``patch_size`` x ``patch_size`` patches; a token is the patch's raw pixels
(D = 3 * patch_size**2), optionally followed by a FIXED random orthogonal projection to ``proj_dim``
(seeded, generated with numpy's frozen ``RandomState`` so every machine builds the same matrix).

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


@register_encoder("patch-pixels")
class PatchPixelEncoder(FrozenEncoder):
    """Raw normalised pixels of a patch grid, optionally randomly projected. See the module doc."""

    name = "patch-pixels"

    def __init__(self, input_size: int = 64, patch_size: int = 16, proj_dim: int | None = 128,
                 seed: int = 0) -> None:
        super().__init__(input_size)
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
        self._raw_dim = raw
        proj = orthogonal_projection(raw, proj_dim, seed) if proj_dim is not None else torch.empty(0)
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
        return {"name": self.name, "input_size": self.input_size, "patch_size": self.patch_size,
                "proj_dim": self.proj_dim, "seed": self.seed}
