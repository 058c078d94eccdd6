"""Torch datasets over one or more episode stores, for the two consumers.

* :class:`WAMSamples` (WAM training): the observation at step t, the action chunk t..t+H-1 and the
  views at t+H (H = 16; past the episode's end the last action is held and the final frame is
  the target, since the scene stays where it ended).
* :class:`WorldModelWindows` (world-model training, paper eq. 1-2): ``history + horizon`` frames at
  stride Δ starting at any stored step s; frame i is step s + iΔ with its images (or cached encoder
  features), its proprio, and the Δ-step action block executed from it, flattened to (Δ·A,).

Views are stacked in the order of the stores' ``cameras`` (their task's); the stores of one dataset must hold
the same task's episodes with the same env settings (``cameras``: a dataset's). A is the task's action size,
P its proprio size.

The train/validation split is by episode, from a hash of (source, seed), so it is the same on every
run and machine and no episode contributes to both sides.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
from collections import Counter, OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from wamplan.data.features import check_features, feature_dir
from wamplan.data.store import EpisodeStore, StoreError, parent_episode, reading


def split_of(source: str, seed: int, val_fraction: float) -> str:
    """'val' for a stable ``val_fraction`` of episodes (by hash of source and seed), else 'train'. A
    counterfactual branch (``branch:<name>``, ``wamplan.data.branch``) goes where its parent episode goes:
    siblings share the parent's history frames, so they must not straddle the split."""
    source, seed = parent_episode(source, seed)
    h = int(hashlib.sha1(f"{source}:{seed}".encode()).hexdigest()[:8], 16) / 0xFFFFFFFF
    return "val" if h < val_fraction else "train"


@dataclass(frozen=True)
class EpisodeRef:
    path: str
    source: str
    seed: int
    length: int
    image_steps: tuple[int, ...]
    image_every: int
    features: str | None  # this episode's feature-cache file, if features are used
    branch_at: tuple[int, int] | None = None  # a branch's (parent's boundary step, parent's step at its step 0)


def index_episodes(stores: Sequence[str | Path], split: str = "all", val_fraction: float = 0.1,
                   features: str | None = None, sources: Sequence[str] | None = None) -> list[EpisodeRef]:
    """The episodes of ``stores`` in ``split`` ('train', 'val' or 'all'), optionally only some sources (one line
    naming the stores' sources if one of ``sources`` is none of them)."""
    if split not in ("train", "val", "all"):
        raise ValueError(f"split must be train, val or all, got {split!r}")
    refs, envs, seen = [], {}, set()
    for root in stores:
        store = EpisodeStore(root)
        envs[str(root)] = dict(store.env, cameras=list(store.cameras))
        fdir = feature_dir(root, features) if features is not None else None
        for p in store.episode_paths():
            feat = None
            if fdir is not None:
                feat = str(fdir / f"{p.stem}.h5")
                if not Path(feat).is_file():
                    raise StoreError(f"{root} has no '{features}' features for {p.name}; run `wamplan wm encode "
                                     f"--data {root}` with the same encoder settings first")
                check_features(feat, features)
            with store.open_episode(p) as f:
                src, seed = str(f.attrs["source"]), int(f.attrs["seed"])
                seen.add(src)
                if sources is not None and src not in sources:
                    continue
                if split != "all" and split_of(src, seed, val_fraction) != split:
                    continue
                branch_at = None
                if src.startswith("branch:"):  # kept here so sibling grouping never reopens the file
                    branch_at = (int(json.loads(f.attrs["policy"])["branch_step"]),
                                 int(json.loads(f.attrs["provenance"])["start_step"]))
                refs.append(EpisodeRef(str(p), src, seed, int(f.attrs["length"]),
                                       tuple(int(s) for s in f["image_steps"][:]), store.image_every, feat, branch_at))
    unknown = [s for s in sources or () if s not in seen]
    if unknown:
        raise StoreError(f"the stores {[str(r) for r in stores]} hold no episodes of source "
                         f"{', '.join(repr(s) for s in unknown)}; their sources are {', '.join(sorted(seen)) or 'none'}"
                         f" (`wamplan data info` lists them); choose among those")
    if len({json.dumps(e, sort_keys=True) for e in envs.values()}) > 1:
        tasks = sorted({e["task"] for e in envs.values()})
        what = f"for different tasks ({', '.join(tasks)})" if len(tasks) > 1 else "with different env settings"
        raise StoreError(f"the stores {list(envs)} were collected {what}; train on stores with the same settings")
    return refs


def stores_cameras(stores: Sequence[str | Path]) -> tuple[str, ...]:
    """The cameras of ``stores`` (one task's; :func:`index_episodes` checks that they agree)."""
    return EpisodeStore(stores[0]).cameras if stores else ()


def open_file_budget() -> int:
    """How many HDF5 files one process keeps open: 512, or half its soft limit on open files (``ulimit -n``) where
    that is lower (at least 16). More open files cost memory and slow every read, and a dataset of more files than
    the limit must still read."""
    return max(16, min(512, resource.getrlimit(resource.RLIMIT_NOFILE)[0] // 2))


class H5Cache:
    """Open HDF5 files lazily, per process (h5py handles must not cross a fork), at most ``max_open`` at a time:
    the least recently read one is closed to make room (re-opening one costs well under a millisecond)."""

    def __init__(self, max_open: int | None = None):
        self.max_open = max_open or open_file_budget()
        self._files: OrderedDict[str, h5py.File] = OrderedDict()
        self._pid = os.getpid()

    def get(self, path: str) -> h5py.File:
        if os.getpid() != self._pid:  # a forked worker: the parent's handles are not ours to read or close
            self._files, self._pid = OrderedDict(), os.getpid()
        f = self._files.get(path)
        if f is not None:
            self._files.move_to_end(path)
            return f
        while len(self._files) >= self.max_open:
            self._files.popitem(last=False)[1].close()
        f = self._files[path] = h5py.File(path, "r")
        return f

    def __len__(self) -> int:
        return len(self._files)

    def __getstate__(self):
        return {"max_open": self.max_open, "_files": OrderedDict(), "_pid": -1}


_ITEM_FIX = ("`wamplan data check STORE` names every damaged episode: delete those and re-run the `wamplan collect` "
             "(or `wamplan wm encode`) that wrote them")


class _EpisodeDataset(Dataset):
    """The body every reader shares: the indexed episodes of ``stores``, a flat list of items (each a tuple
    whose first entry is the episode index), and HDF5 files opened lazily per process."""

    def __init__(self, stores: Sequence[str | Path], split: str, val_fraction: float, features: str | None = None,
                 sources: Sequence[str] | None = None):
        self.episodes = index_episodes(stores, split, val_fraction, features=features, sources=sources)
        self.cameras = stores_cameras(stores)  # the views' order
        self.items: list[tuple[int, ...]] = []
        self._h5 = H5Cache()

    def _require_stride(self, every: int, what: str, fix: str = "") -> None:
        """Every episode's image stride must divide ``every`` (a chunk length or a frameskip)."""
        for e in self.episodes:
            if every % e.image_every:
                raise StoreError(f"{what} {every} is not a multiple of the store's image stride {e.image_every}{fix}")

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, idx: int) -> dict[str, torch.Tensor]:
        with reading(" or ".join(self._files(idx)), fix=_ITEM_FIX):  # a damaged chunk (checksum) or file
            return self._read(idx)

    def _read(self, idx: int) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def _files(self, idx: int) -> list[str]:
        """The files item ``idx`` reads (its episode, and its features where used)."""
        e = self.episodes[self.items[idx][0]]
        return [e.path] + ([e.features] if e.features else [])

    def _item(self, idx: int) -> tuple[EpisodeRef, h5py.File, tuple[int, ...]]:
        """The episode of item ``idx``, its open episode file, and the rest of the item tuple."""
        i, *rest = self.items[idx]
        e = self.episodes[i]
        return e, self._h5.get(e.path), tuple(rest)


class WAMSamples(_EpisodeDataset):
    """Items: ``images`` (V, H, W, 3) uint8 at t, ``proprio`` (P,), ``actions`` (H, A), ``future`` (V, H, W, 3)
    at t+H, plus ``step``. V follows ``cameras`` (the cube's: front, side, wrist)."""

    def __init__(self, stores: Sequence[str | Path], chunk: int = 16, split: str = "train", val_fraction: float = 0.1,
                 sources: Sequence[str] | None = None):
        super().__init__(stores, split, val_fraction, sources=sources)
        self.chunk = chunk
        self._require_stride(chunk, "chunk length")
        # every stored step before the end can start a chunk
        self.items = [(i, k) for i, e in enumerate(self.episodes) for k, t in enumerate(e.image_steps) if t < e.length]

    def _read(self, idx: int) -> dict[str, torch.Tensor]:
        e, f, (k,) = self._item(idx)
        t = e.image_steps[k]
        t_end = min(t + self.chunk, e.length)
        k_end = e.image_steps.index(t_end)
        acts = f["actions"][t:t_end]  # (<=H, A)
        if len(acts) < self.chunk:  # hold the last action past the episode's end
            acts = np.concatenate([acts, np.repeat(acts[-1:], self.chunk - len(acts), 0)])
        return dict(images=torch.from_numpy(np.stack([f["images"][c][k] for c in self.cameras])),  # (V, H, W, 3)
                    proprio=torch.from_numpy(f["proprio"][t]),  # (P,)
                    actions=torch.from_numpy(acts.astype(np.float32)),  # (H, A)
                    future=torch.from_numpy(np.stack([f["images"][c][k_end] for c in self.cameras])),  # (V, H, W, 3)
                    step=torch.tensor(t))


class WorldModelWindows(_EpisodeDataset):
    """Items: ``q`` (T, P), ``a`` (T, Δ·A), and ``z`` (T, V, N, D) cached features (with ``features``) or
    ``images`` (T, V, H, W, 3) uint8, where T = history + horizon frames at stride Δ (``frameskip``).

    ``a[i]`` is the block of Δ actions executed from frame i's step, so frame i+1 = step(frame i, a[i]).
    With ``window_end="frame"`` the last frame may be the episode's last frame on the Δ grid, so the final
    (e.g. seated) frames become prediction targets; the last frame's block, which no loss uses, is then
    padded past the episode's end with its last action. ``"block"`` keeps whole blocks only."""

    def __init__(self, stores: Sequence[str | Path], frameskip: int = 4, history: int = 3, horizon: int = 2,
                 split: str = "train", val_fraction: float = 0.1, features: str | None = None,
                 sources: Sequence[str] | None = None, window_end: str = "block"):
        if window_end not in ("block", "frame"):
            raise ValueError(f"window_end must be block or frame, got {window_end!r}")
        super().__init__(stores, split, val_fraction, features=features, sources=sources)
        self.frameskip, self.frames = frameskip, history + horizon
        self.features = features
        self._require_stride(frameskip, "frameskip", "; collect with --image-every dividing it")
        span = self.frames * frameskip  # steps covered by the frames and the last action block
        if window_end == "frame":
            span -= frameskip  # the last frame itself must exist; its block is padded
        self.items = [(i, k) for i, e in enumerate(self.episodes) for k, s in enumerate(e.image_steps)
                      if s % e.image_every == 0 and s + span <= e.length]

    def _read(self, idx: int) -> dict[str, torch.Tensor]:
        e, f, (k,) = self._item(idx)
        return self._window(e, f, k)

    def _window(self, e: EpisodeRef, f: h5py.File, k: int) -> dict[str, torch.Tensor]:
        """The window of episode ``e`` whose first frame is its stored image ``k``."""
        stride = self.frameskip // e.image_every
        ks = [k + j * stride for j in range(self.frames)]  # image indices of the frames
        steps = [e.image_steps[j] for j in ks]
        acts = f["actions"][steps[0]:steps[-1] + self.frameskip]  # (T·Δ, A), shorter at the episode's end
        if len(acts) < self.frames * self.frameskip:
            acts = np.concatenate([acts, np.repeat(acts[-1:], self.frames * self.frameskip - len(acts), 0)])
        out = dict(q=torch.from_numpy(f["proprio"][steps]),  # (T, P)
                   a=torch.from_numpy(acts.reshape(self.frames, -1).astype(np.float32)),  # (T, Δ·A)
                   steps=torch.tensor(steps))
        if self.features is not None:
            cache = self._h5.get(e.features)
            out["z"] = torch.from_numpy(cache["z"][ks])  # (T, V, N, D) float16
        else:
            out["images"] = torch.from_numpy(np.stack([f["images"][c][ks] for c in self.cameras], 1))  # (T, V, H, W, 3)
        return out


class FeatureFrames(_EpisodeDataset):
    """Items: ``z`` (N, D) cached features of one view of one stored frame and its ``image`` (H, W, 3)
    uint8 (for training the decoder), of the views of ``cameras`` (default: every stored view)."""

    def __init__(self, stores: Sequence[str | Path], features: str, split: str = "train", val_fraction: float = 0.1,
                 cameras: Sequence[str] | None = None, sources: Sequence[str] | None = None):
        super().__init__(stores, split, val_fraction, features=features, sources=sources)
        use = self.cameras if cameras is None else tuple(cameras)
        if unknown := [c for c in use if c not in self.cameras]:
            raise StoreError(f"the stores {list(map(str, stores))} hold no views of {unknown}; their cameras are "
                             f"{list(self.cameras)}")
        self.items = [(i, k, v) for i, e in enumerate(self.episodes) for k in range(len(e.image_steps))
                      for v, c in enumerate(self.cameras) if c in use]

    def _read(self, idx: int) -> dict[str, torch.Tensor]:
        e, f, (k, v) = self._item(idx)
        z = self._h5.get(e.features)["z"][k, v]  # (N, D)
        img = f["images"][self.cameras[v]][k]  # (H, W, 3)
        return dict(z=torch.from_numpy(z), image=torch.from_numpy(img))


class BranchGroups(WorldModelWindows):
    """Items: the sibling branches of one chunk boundary (``wamplan.data.branch``), each as the window whose
    context ends at the boundary (its H_ctx - 1 earlier frames come from the parent's shared past) and which
    runs ``horizon`` frames into the branch's own chunk: ``z`` (G, T, V, N, D) cached features (or ``images``
    (G, T, V, H, W, 3) without ``features``), ``q`` (G, T, P), ``a`` (G, T, Δ·A) and ``steps`` (G, T), with
    T = history + horizon: :class:`WorldModelWindows` items stacked over G siblings.
    The G windows share their context and differ only in the chunk executed from the boundary, so comparing
    their futures teaches what CEM asks of the world model: which of two nearby chunks from one state ends
    where. Siblings are the branches of one parent episode (store, source, seed) at one boundary; branches
    collected with too little ``--branch-context`` for H_ctx frames, or too short for the horizon, are left out.
    ``group`` (default: the most common group size, i.e. the collection's ``--branches``): groups with fewer
    siblings are left out, larger ones keep their first ``group``. :meth:`with_targets` adds each group's planning
    target (``target`` (V, N, D), e.g. the WAM's predicted views at the boundary, encoded) to its item."""

    def __init__(self, stores: Sequence[str | Path], frameskip: int = 4, history: int = 3, horizon: int = 4,
                 group: int | None = None, split: str = "train", val_fraction: float = 0.1,
                 features: str | None = None):
        super().__init__(stores, frameskip, history, horizon, split, val_fraction, features, window_end="frame")
        span = (self.frames - 1) * frameskip  # steps from the first frame to the last
        groups: dict[tuple, list[tuple[int, int]]] = {}
        for i, e in enumerate(self.episodes):
            if e.branch_at is None:
                continue
            boundary, start = e.branch_at  # the parent's boundary step, and its step at the branch's step 0
            first = boundary - start - (history - 1) * frameskip  # the window's first step in the branch episode
            if first < 0 or first not in e.image_steps or first + span > e.length:
                continue
            key = (str(Path(e.path).parent), *parent_episode(e.source, e.seed), boundary)
            groups.setdefault(key, []).append((i, e.image_steps.index(first)))
        sizes = Counter(len(m) for m in groups.values())
        self.group = group or (sizes.most_common(1)[0][0] if sizes else 0)  # default: the collection's --branches
        self.items = [tuple(m[:self.group]) for _, m in sorted(groups.items()) if len(m) >= self.group]
        self.targets: torch.Tensor | None = None  # (len(items), V, N, D) once :meth:`with_targets` set them

    def with_targets(self, targets: torch.Tensor) -> "BranchGroups":
        """Give group i the planning target ``targets[i]`` (``targets`` (len(self), V, N, D)): its items then hold
        ``target`` (V, N, D) too. Returns self."""
        if len(targets) != len(self.items):
            raise ValueError(f"{len(targets)} targets for {len(self.items)} branch groups")
        self.targets = targets
        return self

    def _read(self, idx: int) -> dict[str, torch.Tensor]:
        members = [self._window(self.episodes[i], self._h5.get(self.episodes[i].path), k) for i, k in self.items[idx]]
        out = {k: torch.stack([m[k] for m in members]) for k in members[0]}  # each (G, T, ...)
        if self.targets is not None:
            out["target"] = self.targets[idx]  # (V, N, D)
        return out

    def _files(self, idx: int) -> list[str]:
        return [f for i, _ in self.items[idx] for f in [self.episodes[i].path, self.episodes[i].features] if f]
