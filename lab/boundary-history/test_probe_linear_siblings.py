"""The linear probe's fits: an exactly linear response is explained, noise is not."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

HERE = Path(__file__).parent
_spec = importlib.util.spec_from_file_location("probe_linear_siblings", HERE / "probe_linear_siblings.py")
probe = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(probe)


def groups(linear: bool, m: int = 40, g: int = 6, f: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    """m groups of g siblings: commands s (m, g, 3) and frames z (m, g, f), each group with its own map."""
    gen = torch.Generator().manual_seed(0)
    s = torch.randn(m, g, 3, generator=gen)
    maps = torch.randn(m, 3, f, generator=gen)
    z = torch.einsum("mgk,mkf->mgf", s, maps) if linear else torch.randn(m, g, f, generator=gen)
    return z - z.mean(1, keepdim=True), s - s.mean(1, keepdim=True)


def test_a_states_own_linear_response_is_explained_and_noise_is_not():
    z, s = groups(linear=True)
    assert probe.local_r2(z, s, 1e-4) > 0.99
    z, s = groups(linear=False)
    assert probe.local_r2(z, s, 1.0) < 0.05


def test_a_shared_map_is_recovered_by_ridge():
    gen = torch.Generator().manual_seed(1)
    x, w = torch.randn(200, 5, generator=gen), torch.randn(5, 7, generator=gen)
    assert torch.allclose(probe.ridge(x, x @ w, 1e-6), w, atol=1e-4)
    assert probe.r2(x @ w, x @ w) == 1.0 and probe.r2(torch.zeros(200, 7), x @ w) == 0.0
