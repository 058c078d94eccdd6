"""The episode store: one directory, one HDF5 file per episode, a manifest that pins the env settings.

Why HDF5 (h5py): chunked, compressed, random access by frame, one self-describing file per episode
(ManiSkill's own trajectory format is HDF5 too), and a file that is written under a temporary name and
``os.replace``-d into place is either complete or absent, so a killed collection loses at most the
episodes in flight and never leaves a half-written episode behind.

Layout::

    DIR/store.json                         schema version, the task (``TaskSpec.describe()``), env settings (task
                                           kwargs), image stride, cameras, provenance of the store's creation
    DIR/episodes/<source>-s<seed>.h5       one episode (``source`` with ':' and '/' made safe)

A store records one task; a store whose manifest names none (every store written before tasks) holds
``cube-insertion`` episodes (:data:`LEGACY_TASK`).

Episode schema (T = executed control steps; step t's action is applied to the state at step t; A, P and the
cameras are the task's, the stages its ``stages``)::

    attrs: seed, source, success, outcome, length (= T), policy (JSON), provenance (JSON), reached (JSON)
    actions         (T, A)      float32  action executed at step t (after clipping to [-1, 1])
    proprio         (T+1, P)    float32  proprio at steps 0..T
    stages          (T+1, S)    bool     the task's stage flags at steps 0..T (cube: grasped, lifted, aligned,
                                         descended, seated)
    cube_pose       (T+1, 7)    float32  privileged cube pose (xyz, wxyz quaternion); tasks whose privileged
                                         state has one (cube-insertion)
    tcp_pose        (T+1, 7)    float32  privileged TCP pose; robots with a TCP
    target_pose     (T+1, 7)    float32  privileged pose of where the held object must go; tasks whose target moves
                                         with the seed (stack-cube: the cube to stack on)
    sim_state       (T+1, S')   float32  ManiSkill ``get_state()`` (enough to restore physics and re-render)
    drive_targets   (T+1, J)    float32  joint drive targets (``get_state`` leaves them out)
    image_steps     (K,)        int32    steps whose images are stored: every ``image_every``-th step and T
    images/<camera> (K, H, W, 3) uint8   one chunk per frame, gzip-compressed

Damage is found, not only truncation: every dataset carries HDF5's per-chunk fletcher32 checksum and the file's
metadata (attributes, headers, chunk indexes) the checksums of the HDF5 1.10 file format, so reading a damaged
part fails instead of returning other numbers; :func:`verify_episode` reads every byte of a file (``wamplan data
check``). Stores written before checksums read as before (their damage is found only where it breaks the
decompression or the file's structure).

Frames every ``image_every`` steps are what the consumers need: the world model's frameskip Δ and the
WAM's chunk length H must be multiples of it (Δ=4, H=16 with the default 4; the paper's Δ=5 needs 1 or 5).
"""

from __future__ import annotations

import errno
import json
import os
import re
import resource
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import h5py
import numpy as np

from wamplan.envs.spec import TaskSpec, check_same_task, get_task
from wamplan.errors import UserError, not_a, reason
from wamplan.locks import LOCK_FILE

SCHEMA_VERSION = 1
MANIFEST = "store.json"
EPISODES = "episodes"
from wamplan.envs.spec import DEFAULT_TASK as LEGACY_TASK  # noqa: E402  (what records no task means)
POSES = ("cube_pose", "tcp_pose", "target_pose")  # privileged poses, stored where the task's privileged state has them


class StoreError(UserError):
    """A directory is not a (compatible, intact) wamplan episode store."""


RECOLLECT = "delete it and re-run the same `wamplan collect` command to re-collect that seed"

# Camera frames (K, H, W, 3) uint8, one chunk a frame; gzip level 1: on these noisy renders faster to write than
# higher levels and no larger (docs/results.md, Timings).
IMAGE_COMPRESSION = dict(compression="gzip", compression_opts=1)

# the HDF5 file format of new episode files: 1.10's, whose metadata and chunk indexes carry checksums (h5py's
# default, the earliest format, has none; 1.8's leaves the chunk index unchecked); HDF5 >= 1.10 (2016) reads it.
# With fletcher32 on every dataset, a damaged chunk or index fails to read instead of returning other numbers
# (measured: docs/results.md).
CHECKSUMMED_FORMAT = ("v110", "v110")


@contextmanager
def reading(path: str | Path, fix: str = RECOLLECT) -> Iterator[None]:
    """Turn a failed read of the HDF5 file ``path`` (a checksum mismatch, a damaged chunk, a missing dataset) into
    a one-line :class:`StoreError` that names the file and ``fix``. Only a failure raised inside h5py counts as a
    failed read: any other error of the ``with`` body (a computation on what was read) passes through unchanged."""
    try:
        yield
    except (OSError, KeyError, ValueError, RuntimeError) as e:
        if isinstance(e, OSError) and (e.errno == errno.EMFILE or "Too many open files" in str(e)):
            raise StoreError(f"too many open files while reading {path} (the files are not damaged): raise the "
                             f"limit (`ulimit -n`, now {resource.getrlimit(resource.RLIMIT_NOFILE)[0]}) and run it "
                             f"again") from None
        if not _raised_in_h5py(e):
            raise
        raise StoreError(f"{path} is damaged, a read failed ({reason(e)}); {fix}") from None


def _raised_in_h5py(e: BaseException) -> bool:
    """Whether the innermost Python frame of ``e``'s traceback is h5py's (a read of the file failed)."""
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and str(tb.tb_frame.f_globals.get("__name__", "")).startswith("h5py")


BRANCH_SEED_FACTOR = 1000  # a counterfactual branch j of parent seed s has seed s * 1000 + j (wamplan.data.branch)


def parent_episode(source: str, seed: int) -> tuple[str, int]:
    """The episode a counterfactual branch (``branch:<name>``) was cut from; any other episode is its own."""
    if source.startswith("branch:"):
        return "policy:" + source[len("branch:"):], int(seed) // BRANCH_SEED_FACTOR
    return source, int(seed)


def source_tag(source: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", source)


@dataclass
class EpisodeData:
    """One episode in memory, as collected (see the module docstring for shapes)."""

    seed: int
    source: str
    success: bool
    outcome: str
    actions: np.ndarray
    proprio: np.ndarray
    stages: np.ndarray
    cube_pose: np.ndarray | None  # None: the task's privileged state has no cube pose
    tcp_pose: np.ndarray | None  # None: the robot has no TCP
    sim_state: np.ndarray
    drive_targets: np.ndarray
    image_steps: np.ndarray
    images: dict[str, np.ndarray]
    reached: dict[str, bool]
    policy: dict[str, Any]
    provenance: dict[str, Any]
    target_pose: np.ndarray | None = None  # None: the task's target does not move (or it records none)

    @property
    def length(self) -> int:
        return int(len(self.actions))

    @classmethod
    def logged(cls, task: TaskSpec, seed: int, actions: np.ndarray, proprio: np.ndarray,
               images: dict[str, np.ndarray], image_steps: Sequence[int], *, image_every: int = 4,
               source: str = "robot", success: bool = False, outcome: str = "logged",
               provenance: dict | None = None) -> EpisodeData:
        """An episode recorded without a simulator (a real robot's log) for ``task``: what the world model and
        TinyWAM train on, the simulator's fields (stages, poses, physics state) left empty.
        ``actions`` (T, A) as executed, ``proprio`` (T+1, P) at steps 0..T, ``images[camera]`` (K, H, W, 3) uint8 at
        ``image_steps`` (K,): 0, ``image_every``, 2 ``image_every``, ... up to T, and T (the store's ``image_every``;
        the world model pairs frames with actions by that spacing). One :class:`StoreError` names a shape, camera or
        frame spacing that does not fit."""
        actions, proprio = np.asarray(actions, np.float32), np.asarray(proprio, np.float32)
        steps = np.asarray(image_steps, np.int32)
        t = len(actions)
        problems = []
        if actions.shape != (t, task.action_dim):
            problems.append(f"actions are {actions.shape}, want (T, {task.action_dim})")
        if proprio.shape != (t + 1, task.proprio_dim):
            problems.append(f"proprio is {proprio.shape}, want (T+1, {task.proprio_dim}) = ({t + 1}, {task.proprio_dim})")
        for name, arr in (("actions", actions), ("proprio", proprio)):
            bad = np.flatnonzero(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1)) if arr.ndim >= 1 and arr.size else []
            if len(bad):
                problems.append(f"{name} hold NaN or inf at step(s) {bad[:5].tolist()}{' ...' * (len(bad) > 5)}, "
                                f"want finite numbers")
        if sorted(images) != sorted(task.cameras):
            problems.append(f"images are of cameras {sorted(images)}, want {sorted(task.cameras)}")
        want = list(range(0, t + 1, image_every)) + ([t] if t % image_every else [])
        if steps.ndim != 1 or steps.tolist() != want:
            have = steps.ravel().tolist()
            gap = next((f"step {w} missing or moved (has {h})" for w, h in zip(want, have) if w != h),
                       f"{len(have)} frames for {len(want)}")
            problems.append(f"image_steps must be 0, {image_every}, {2 * image_every}, ... up to T={t} and T "
                            f"(every {image_every}th step): {gap}")
        for cam, arr in images.items():
            a = np.asarray(arr)
            if a.dtype != np.uint8 or a.ndim != 4 or a.shape[0] != len(steps) or a.shape[-1] != 3:
                problems.append(f"images[{cam!r}] is {a.dtype} {a.shape}, want uint8 ({len(steps)}, H, W, 3)")
        if problems:
            raise StoreError(f"episode {seed} does not fit task '{task.name}': {'; '.join(problems)}")
        empty = np.zeros((t + 1, 0), np.float32)
        return cls(seed=seed, source=source, success=success, outcome=outcome, actions=actions, proprio=proprio,
                   stages=np.zeros((t + 1, 0), bool), cube_pose=None, tcp_pose=None, sim_state=empty,
                   drive_targets=empty, image_steps=steps, images={c: np.asarray(images[c]) for c in task.cameras},
                   reached={}, policy={"name": source}, provenance=provenance or {})


TMP_PREFIX = ".tmp-"  # files being written; never *.h5 until complete, so listings cannot see them


@contextmanager
def atomic_h5(final: Path, **kwargs: Any) -> Iterator[h5py.File]:
    """Write the HDF5 file ``final`` under a temporary name, fsync it, then rename it into place: a reader
    (or a kill -9) sees the whole file or none of it. ``kwargs`` go to ``h5py.File`` (e.g. ``libver``)."""
    tmp = final.with_name(f"{TMP_PREFIX}{final.stem}-{os.getpid()}.part")
    with h5py.File(tmp, "w", **kwargs) as f:
        yield f
        f.flush()
        os.fsync(f.id.get_vfd_handle())
    os.replace(tmp, final)


class EpisodeStore:
    """Create or open a store. ``task`` (the spec collected), ``env`` (task kwargs) and ``image_every`` must match
    an existing store; creating one records ``task`` (default: the task ``env`` names)."""

    def __init__(self, root: str | Path, *, create: bool = False, env: dict | None = None, image_every: int | None = None,
                 provenance: dict | None = None, task: TaskSpec | None = None):
        self.root = Path(root)
        man = self.root / MANIFEST
        if self.root.exists() and not self.root.is_dir():
            raise StoreError(f"{self.root} is a file, not an episode store directory; pass a directory (for "
                             f"collecting: a new or empty one)")
        if man.is_file():
            self.manifest = self._read_manifest(man)
            if task is not None:
                check_same_task(task.name, self.task_name, f"store {self.root}")
            if env is not None and self.env != env:
                stored = self.env
                diff = {k: (stored.get(k), env.get(k)) for k in set(env) | set(stored) if stored.get(k) != env.get(k)}
                raise StoreError(f"{self.root} was collected with other env settings {diff} (stored, requested); "
                                 f"use another --out directory or the stored settings")
            if image_every is not None and self.manifest["image_every"] != image_every:
                raise StoreError(f"{self.root} stores images every {self.manifest['image_every']} steps, not "
                                 f"{image_every}; use another --out directory or --image-every {self.manifest['image_every']}")
        elif create:
            there = [p.name for p in self.root.iterdir()] if self.root.exists() else []
            if any(name not in (EPISODES, LOCK_FILE) for name in there):  # a collector's lock alone: still empty
                raise StoreError(f"{self.root} exists and is not a wamplan episode store; choose an empty or new --out")
            if env is None or image_every is None:
                raise ValueError("creating a store needs env and image_every")
            task = task or get_task(env.get("task", LEGACY_TASK))
            if env.get("task", task.name) != task.name:
                raise ValueError(f"env settings of task {env['task']} given for a store of task {task.name}")
            self.root.mkdir(parents=True, exist_ok=True)
            self.manifest = dict(format="wamplan-episode-store", schema_version=SCHEMA_VERSION, task=task.describe(),
                                 env=env, image_every=int(image_every), cameras=list(task.cameras),
                                 provenance=provenance or {})
            tmp = man.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(self.manifest, indent=2) + "\n")
            os.replace(tmp, man)
        else:
            raise StoreError(not_a(self.root, MANIFEST, "a wamplan episode store",
                                   f"wamplan collect --out {self.root}", also=("wamplan data import",)))
        (self.root / EPISODES).mkdir(exist_ok=True)

    @staticmethod
    def _read_manifest(path: Path) -> dict:
        try:
            m = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise StoreError(f"{path} is damaged ({e}); restore it or collect into a new directory") from e
        if not isinstance(m, dict) or m.get("format") != "wamplan-episode-store":
            raise StoreError(f"{path} is not a wamplan episode store manifest; check the path")
        if m.get("schema_version") != SCHEMA_VERSION:
            raise StoreError(f"{path} has schema version {m.get('schema_version')}, this wamplan reads "
                             f"{SCHEMA_VERSION}; re-collect it or use a matching wamplan version")
        every, env = m.get("image_every"), m.get("env")
        bad = (f"image_every {every!r} is not a whole number of steps >= 1"
               if not isinstance(every, int) or isinstance(every, bool) or every < 1
               else None if isinstance(env, dict) else f"env {env!r} is not a JSON object of env settings")
        if bad:
            raise StoreError(f"{path} is damaged ({bad}); restore it or collect into a new directory")
        return m

    # ------------------------------------------------------------------ paths
    @property
    def image_every(self) -> int:
        return int(self.manifest["image_every"])

    @property
    def env(self) -> dict:
        """The env settings (``EnvConfig.task_kwargs()``), with the task's name (a legacy store's: cube-insertion)."""
        return {"task": self.task_name, **self.manifest["env"]}

    @property
    def task_name(self) -> str:
        """The name of the task the store was collected in (:data:`LEGACY_TASK` where it records none)."""
        recorded = self.manifest.get("task") or {}
        return str(recorded.get("task") or self.manifest["env"].get("task") or LEGACY_TASK)

    @property
    def task(self) -> TaskSpec:
        """The registered spec of the store's task; one line if it no longer describes what the store recorded."""
        spec = get_task(self.task_name)
        recorded = self.manifest.get("task")
        if recorded is not None and recorded != spec.describe():
            now = spec.describe()
            diff = {k: (recorded.get(k), now.get(k)) for k in set(recorded) | set(now) if recorded.get(k) != now.get(k)}
            raise StoreError(f"{self.root} was collected in task '{spec.name}' as it was then; the registered task "
                             f"differs {diff} (stored, registered): collect the store again for the task as it is")
        return spec

    @property
    def cameras(self) -> tuple[str, ...]:
        """The cameras whose views every episode stores, in the order models stack them."""
        cams = self.manifest.get("cameras")
        return tuple(cams) if cams else self.task.cameras

    def episode_path(self, source: str, seed: int) -> Path:
        return self.root / EPISODES / f"{source_tag(source)}-s{int(seed):07d}.h5"

    def episode_paths(self) -> list[Path]:
        return sorted(p for p in (self.root / EPISODES).glob("*.h5") if not p.name.startswith("."))

    def _files_of(self, source: str) -> dict[int, Path]:
        """seed -> episode file, of the files named for ``source``."""
        prefix = source_tag(source) + "-s"
        return {int(p.stem[len(prefix):]): p for p in self.episode_paths() if p.stem.startswith(prefix)
                and p.stem[len(prefix):].isdigit()}

    def finished_seeds(self, source: str) -> set[int]:
        return set(self._files_of(source))

    def check_source(self, source: str) -> None:
        """Refuse ``source`` when the store's files under its name were written by another source: file names
        keep only letters, digits and ``_.-`` of a source, so ``policy:a+b`` and ``policy:a_b`` share them."""
        for p in list(self._files_of(source).values())[:1]:
            with self.open_episode(p) as f:
                other = str(f.attrs["source"])
            if other != source:
                raise StoreError(f"{self.root} holds episodes of source '{other}' under the file names of "
                                 f"'{source}'; collect into another --out (or rename the checkpoint directory)")

    def clean_partial(self) -> int:
        """Delete temporary files that a killed writer left behind; returns how many."""
        n = 0
        for p in (self.root / EPISODES).glob(TMP_PREFIX + "*"):
            p.unlink(missing_ok=True)
            n += 1
        return n

    # ------------------------------------------------------------------ write
    def write(self, ep: EpisodeData) -> Path:
        """Write one episode atomically (temporary file, fsync, rename)."""
        final = self.episode_path(ep.source, ep.seed)
        if final.exists():
            raise StoreError(f"{final} exists already; a store never overwrites an episode")
        with atomic_h5(final, libver=CHECKSUMMED_FORMAT) as f:
            f.attrs.update(seed=ep.seed, source=ep.source, success=bool(ep.success), outcome=ep.outcome, length=ep.length,
                           policy=json.dumps(ep.policy), provenance=json.dumps(ep.provenance),
                           reached=json.dumps(ep.reached))
            for name in ("actions", "proprio", *POSES, "sim_state", "drive_targets"):
                if getattr(ep, name) is not None:  # a pose the task's privileged state lacks is left out
                    f.create_dataset(name, data=np.asarray(getattr(ep, name), np.float32), fletcher32=True)
            f.create_dataset("stages", data=np.asarray(ep.stages, bool), fletcher32=True)
            f.create_dataset("image_steps", data=np.asarray(ep.image_steps, np.int32), fletcher32=True)
            g = f.create_group("images")
            for cam, arr in ep.images.items():  # (K, H, W, 3) uint8
                g.create_dataset(cam, data=arr, chunks=(1, *arr.shape[1:]), fletcher32=True, **IMAGE_COMPRESSION)
        return final

    # ------------------------------------------------------------------ read
    @contextmanager
    def open_episode(self, path: str | Path) -> Iterator[h5py.File]:
        """The episode file ``path``, open for reading; a file that is not an episode, or a read in the ``with``
        body that fails (see :func:`reading`), raises a one-line :class:`StoreError` naming the file."""
        try:
            f = h5py.File(path, "r")
        except OSError as e:
            raise StoreError(f"episode file {path} is damaged or not a wamplan episode ({e}); {RECOLLECT}") from None
        with f:
            try:
                f["actions"], f["image_steps"]  # noqa: B018  (raises if the file is not an episode)
            except (OSError, KeyError) as e:
                raise StoreError(f"episode file {path} is damaged or not a wamplan episode ({e}); {RECOLLECT}") from None
            with reading(path):
                yield f

    def meta(self, path: str | Path) -> dict[str, Any]:
        """One episode's attributes (cheap: no arrays are read); a :class:`StoreError` naming a damaged file."""
        with self.open_episode(path) as f:
            return dict(path=str(path), seed=int(f.attrs["seed"]), source=str(f.attrs["source"]),
                        success=bool(f.attrs["success"]), outcome=str(f.attrs["outcome"]),
                        length=int(f.attrs["length"]), frames=int(f["image_steps"].shape[0]))

    def iter_meta(self) -> Iterator[dict[str, Any]]:
        """Per-episode attributes (cheap: no arrays are read)."""
        for p in self.episode_paths():
            yield self.meta(p)

    def load(self, path: str | Path) -> EpisodeData:
        with self.open_episode(path) as f:
            return EpisodeData(seed=int(f.attrs["seed"]), source=str(f.attrs["source"]), success=bool(f.attrs["success"]),
                               outcome=str(f.attrs["outcome"]), actions=f["actions"][:], proprio=f["proprio"][:],
                               stages=f["stages"][:], **{k: f[k][:] if k in f else None for k in POSES},
                               sim_state=f["sim_state"][:], drive_targets=f["drive_targets"][:],
                               image_steps=f["image_steps"][:], images={c: f["images"][c][:] for c in f["images"]},
                               reached=json.loads(f.attrs["reached"]), policy=json.loads(f.attrs["policy"]),
                               provenance=json.loads(f.attrs["provenance"]))


def describe_stores(stores: Sequence[str | Path], sources: Sequence[str] | None = None) -> dict[str, Any]:
    """The identity of a training set drawn from ``stores``: their absolute paths, the sources used, and
    the count and a hash of their episode files (a store that gained or lost episodes is other data)."""
    import hashlib

    names = [f"{i}:{p.name}" for i, s in enumerate(stores) for p in EpisodeStore(s).episode_paths()]
    digest = hashlib.sha1("\n".join(sorted(names)).encode()).hexdigest()[:12]
    return {"stores": [str(Path(s).resolve()) for s in stores], "sources": list(sources) if sources else None,
            "episodes": f"{len(names)} episode files, sha1 {digest}"}


def stores_task(stores: Sequence[str | Path]) -> tuple[TaskSpec, tuple[str, ...]]:
    """The task and the cameras (in the order their views are stacked) of ``stores``; one line when they hold
    episodes of different tasks or cameras (one run trains on one task)."""
    if not stores:
        raise UserError("--data needs at least one episode store directory")
    first = EpisodeStore(stores[0])
    for root in stores[1:]:
        other = EpisodeStore(root)
        if other.task_name != first.task_name or other.cameras != first.cameras:
            raise UserError(f"--data mixes tasks: {stores[0]} holds task '{first.task_name}' (cameras "
                            f"{list(first.cameras)}), {root} task '{other.task_name}' (cameras {list(other.cameras)}); "
                            f"train on the stores of one task")
    return first.task, first.cameras


def verify_episode(path: str | Path) -> tuple[str | None, bool]:
    """Read every byte of the episode file ``path`` through HDF5, which checks each chunk's checksum where the
    file has them: ``(the problem, or None; whether every dataset carries a checksum)``."""
    checked = True
    try:
        with h5py.File(path, "r") as f:
            for key in ("seed", "source", "success", "outcome", "length", "policy", "provenance", "reached"):
                v = f.attrs[key]
                if key in ("policy", "provenance", "reached"):
                    json.loads(v)
            datasets: list[h5py.Dataset] = []
            f.visititems(lambda _, obj: datasets.append(obj) if isinstance(obj, h5py.Dataset) else None)
            for name in ("actions", "image_steps", "images"):
                f[name]  # noqa: B018  (raises if the file is not an episode)
            if not len(f["images"]):
                raise KeyError("the episode stores no camera's images")
            for ds in datasets:
                checked &= bool(ds.fletcher32)
                step = max(1, ds.chunks[0]) * 16 if ds.chunks else max(1, len(ds))  # bounded memory for images
                for i in range(0, max(len(ds), 1), step):
                    ds[i:i + step]
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        return reason(e), checked
    return None, checked
