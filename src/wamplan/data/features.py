"""Encode a store's images once with a frozen encoder and cache the features beside it.

    DIR/features/<key>/<episode>.h5     dataset ``z`` (K, V, N, D) float16, one row per stored frame, the
                                        views in the store's ``cameras`` order; attrs: encoder config (JSON)

The key is the encoder's name and a hash of its whole configuration (input size, patch size,
projection, dtype, ...; not the local path of its weights), ``feature_key(encoder.config_dict())``, e.g.
``patch-pixels-1a2b3c4d``: an encoder with other settings gets a fresh cache, never another's features.
Readers check every file's stored configuration against the key they were asked for.

One file per episode, written under a temporary name and renamed, so an interrupted encoding resumes
where it stopped and training never runs the encoder per batch.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Iterator

import torch

from wamplan.data.store import CHECKSUMMED_FORMAT, TMP_PREFIX, EpisodeStore, StoreError, atomic_h5, reading


def feature_key(encoder_config: dict[str, Any]) -> str:
    """'<name>-<hash of the config>': what a feature cache is keyed and checked by (the path is left out)."""
    cfg = {k: v for k, v in encoder_config.items() if k != "path"}
    digest = hashlib.sha1(json.dumps(cfg, sort_keys=True).encode()).hexdigest()[:8]
    return f"{cfg['name']}-{digest}"


def feature_dir(root: str | Path, key: str) -> Path:
    return Path(root) / "features" / key


def check_features(path: str | Path, key: str) -> None:
    """Raise a one-line StoreError if the cached features in ``path`` were not made by the encoder of ``key``."""
    import h5py

    with reading(path, fix="delete it and run `wamplan wm encode` again to re-encode that episode"):
        with h5py.File(path, "r") as f:
            made = json.loads(f.attrs["encoder"])
    if feature_key(made) != key:
        raise StoreError(f"{path} holds features of encoder {made}, not of '{key}'; delete {Path(path).parent} "
                         f"and run `wamplan wm encode` again")


def encode_store(root: str | Path, encoder, batch_size: int = 64) -> Iterator[str]:
    """Encode every episode of ``root`` not yet cached; yields the episode names as they finish. A store whose
    features are all cached is only read (it may be read-only); one that needs encoding and cannot be written
    is refused in one line before any encoding."""
    from wamplan.errors import require_writable

    store = EpisodeStore(root)
    cameras = store.cameras
    key = feature_key(encoder.config_dict())
    out_dir = feature_dir(root, key)
    todo = []
    for path in store.episode_paths():
        final = out_dir / f"{path.stem}.h5"
        if final.exists():
            check_features(final, key)
        else:
            todo.append(path)
    if not todo:
        return
    require_writable(out_dir, "--data")  # the cache lives in the store
    out_dir.mkdir(parents=True, exist_ok=True)
    for p in out_dir.glob(TMP_PREFIX + "*"):
        p.unlink()
    cfg = json.dumps(encoder.config_dict())
    for path in todo:
        final = out_dir / f"{path.stem}.h5"
        with store.open_episode(path) as f:
            frames = {c: f["images"][c][:] for c in cameras}  # (K, H, W, 3) each
        views = [encoder.encode_batched(frames[c], batch_size) for c in cameras]  # V x (K, N, D)
        z = torch.stack(views, dim=1).to(torch.float16).numpy()  # (K, V, N, D)
        with atomic_h5(final, libver=CHECKSUMMED_FORMAT) as g:
            g.create_dataset("z", data=z, chunks=(1, *z.shape[1:]), fletcher32=True)
            g.attrs["encoder"] = cfg
        yield path.stem
