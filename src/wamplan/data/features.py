"""Encode a store's images once with a frozen encoder and cache the features beside it.

    DIR/features/<encoder>/<episode>.h5     dataset ``z`` (K, V, N, D) float16, one row per stored frame,
                                            attrs: encoder config (JSON)

One file per episode, written under a temporary name and renamed, so an interrupted encoding resumes
where it stopped and training never runs the encoder per batch.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from wamplan.data.store import TMP_PREFIX, EpisodeStore, atomic_h5
from wamplan.policies.base import CAMERAS


def feature_dir(root: str | Path, encoder_name: str) -> Path:
    return Path(root) / "features" / encoder_name


@torch.inference_mode()
def encode_frames(encoder, images: np.ndarray, batch_size: int = 64) -> np.ndarray:
    """images (M, H, W, 3) uint8 -> features (M, N, D) float16."""
    out = []
    for i in range(0, len(images), batch_size):
        x = torch.from_numpy(images[i:i + batch_size]).to(encoder.device)  # (b, H, W, 3)
        out.append(encoder.encode(x).to(torch.float16).cpu().numpy())  # (b, N, D)
    return np.concatenate(out)


def encode_store(root: str | Path, encoder, batch_size: int = 64) -> Iterator[str]:
    """Encode every episode of ``root`` not yet cached; yields the episode names as they finish."""
    store = EpisodeStore(root)
    out_dir = feature_dir(root, encoder.name)
    out_dir.mkdir(parents=True, exist_ok=True)
    for p in out_dir.glob(TMP_PREFIX + "*"):
        p.unlink()
    cfg = json.dumps(encoder.config_dict())
    for path in store.episode_paths():
        final = out_dir / f"{path.stem}.h5"
        if final.exists():
            continue
        with store.open_episode(path) as f:
            views = [encode_frames(encoder, f["images"][c][:], batch_size) for c in CAMERAS]  # V x (K, N, D)
        z = np.stack(views, axis=1)  # (K, V, N, D)
        with atomic_h5(final) as g:
            g.create_dataset("z", data=z, chunks=(1, *z.shape[1:]))
            g.attrs["encoder"] = cfg
        yield path.stem
