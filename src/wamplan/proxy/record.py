"""``wamplan serve --record DIR``: every session the proxy answers, written as episodes of an episode store
(:meth:`~wamplan.data.store.EpisodeData.logged`) that ``wamplan wm train --data DIR`` trains on.

What an episode holds: the views and proprio the robot posted at each chunk boundary, the actions it ran between
boundaries (the ``executed_actions`` it sent, else the chunk the proxy answered), and the in-chunk frames of
``chunk_frames`` that fall on the store's frame grid (``--record-every``; default: the chunk, so boundary frames
only, which is what a boundary-history world model, ``wm train --frameskip <chunk>``, reads). Proprio between
frames is not sent by a client: those steps repeat the last one posted (provenance says so). The chunk answered at
an episode's last boundary has no frame after it and is not kept.

Crash safety: an episode in progress is a journal, ``DIR/in-progress/<n>-<session>/``, one file per boundary
written under a temporary name and renamed into place. When the episode ends (a new episode of the session: reset,
idle, a new seed; the session dropped or evicted; the proxy shut down) the journal becomes one episode file,
written atomically by the store, and is removed. A proxy that was killed leaves its journals: the next ``serve
--record DIR`` finalises each into an episode whose outcome is ``interrupted`` and prints its name; a journal
with less than one chunk is removed and named. A journal whose proxy still runs is locked (``flock``) and left
alone.

A chunk whose grid frames were not all sent (``--record-every`` shorter than the chunk) cannot be stored on the
grid: the episode ends at the boundary before it and a new one starts at the boundary after it (logged).
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import shutil
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from wamplan.data.store import MANIFEST, EpisodeData, EpisodeStore, StoreError, source_tag
from wamplan.envs.spec import Observation, TaskSpec
from wamplan.errors import UserError, reason, require_dir, require_own_dir
from wamplan.provenance import provenance

log = logging.getLogger(__name__)

JOURNALS = "in-progress"
META = "meta.json"
LOCK = "lock"
SOURCE_PREFIX = "proxy:"  # an episode's source: proxy:<robot>


def check_record_dir(path: str | Path) -> Path:
    """Refuse, in one line and before anything loads, a record directory that cannot be written (a file in the
    way, a read-only filesystem, missing permissions) or that holds something other than an episode store."""
    p = require_dir(path, "--record")
    require_own_dir(p, (MANIFEST,), "an episode store", "--record")
    return p


def _atomic_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(f".tmp-{path.name}")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


class Journal:
    """One episode in progress: its directory, the boundary last written and what the robot reported of the chunk
    since (``ran``: the actions it ran, ``frames``: in-chunk frames by step)."""

    def __init__(self, path: Path, number: int, key: str, start: int, seed: int, chunk: int):
        self.path, self.number, self.key, self.start = path, number, key, start
        self.last: int | None = None  # the global step of the last boundary written
        self.answered: np.ndarray | None = None  # (H, A) the chunk answered there
        self.ran: np.ndarray | None = None  # (k, A) what the robot said it ran of it
        self.frames: dict[int, Observation] = {}
        self.lock = threading.Lock()
        self.closed = False
        path.mkdir(parents=True)
        tmp = path / f".tmp-{META}"  # a journal without its meta.json was killed as it started: removed on recovery
        tmp.write_text(json.dumps({"number": number, "session": key, "start_step": start, "episode_seed": seed,
                                   "chunk_length": chunk, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}) + "\n")
        os.replace(tmp, path / META)
        self._lock_fd = os.open(path / LOCK, os.O_CREAT | os.O_RDWR, 0o644)
        fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held while this process records it

    def release(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def gap(self, t: int, every: int) -> str | None:
        """Why the chunk ending at boundary ``t`` cannot join the episode on its frame grid, or None."""
        p = self.last
        if p is None:
            return None
        if t <= p:
            return f"step {t} does not follow step {p}"
        acts = self.ran if self.ran is not None else self.answered
        if acts is None or len(acts) < t - p:
            return f"the {t - p} steps from {p} to {t} have {0 if acts is None else len(acts)} actions"
        missing = [g for g in range(p + 1, t) if (g - self.start) % every == 0 and g not in self.frames]
        return f"no frames at steps {missing} (the record grid: every {every} steps)" if missing else None

    def write_boundary(self, obs: Observation, answered: np.ndarray, every: int) -> None:
        """Append boundary ``obs`` (and what ran since the last one) to the journal, atomically."""
        t, arrays = obs.step, {}
        arrays["step"] = np.int64(t)
        arrays["proprio"] = np.asarray(obs.proprio, np.float32)  # (P,)
        arrays["answered"] = np.asarray(answered, np.float32)  # (H, A)
        for cam, img in obs.images.items():
            arrays[f"img_{cam}"] = np.asarray(img, np.uint8)  # (H, W, 3)
        if self.last is not None:
            acts = self.ran if self.ran is not None else self.answered
            arrays["actions"] = np.asarray(acts[: t - self.last], np.float32)  # (t - last, A)
            arrays["executed_sent"] = np.bool_(self.ran is not None)
            grid = sorted(s for s in self.frames if self.last < s < t and (s - self.start) % every == 0)
            kept = [self.frames[s] for s in sorted(s for s in self.frames if self.last < s < t)]
            arrays["frame_steps"] = np.asarray([f.step for f in kept], np.int64)  # (k,)
            if kept:
                arrays["frame_proprio"] = np.stack([np.asarray(f.proprio, np.float32) for f in kept])  # (k, P)
            for cam in obs.images:
                if grid:
                    arrays[f"frame_img_{cam}"] = np.stack([np.asarray(self.frames[s].images[cam], np.uint8)
                                                           for s in grid])  # (g, H, W, 3)
            arrays["grid_steps"] = np.asarray(grid, np.int64)  # (g,)
        _atomic_npz(self.path / f"b{t - self.start:07d}.npz", arrays)
        self.last, self.answered, self.ran, self.frames = t, np.asarray(answered, np.float32), None, {}


def build_episode(path: Path, task: TaskSpec, every: int, outcome: str,
                  ended_by: str) -> tuple[EpisodeData | None, str]:
    """The episode a journal holds (its longest readable, gap-free prefix) -> (episode or None, what was found)."""
    meta = json.loads((path / META).read_text())
    start = int(meta["start_step"])
    files = sorted(path.glob("b*.npz"))
    frames: dict[int, tuple[dict[str, np.ndarray] | None, np.ndarray]] = {}  # local step -> (views, proprio)
    actions: list[np.ndarray] = []
    last, note, executed = None, "", 0
    for f in files:
        try:
            with np.load(f, allow_pickle=False) as z:
                z = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
            note = f"; {f.name} is damaged (not a whole .npz), the episode ends before it"
            break
        t = int(z["step"]) - start
        add = {t: ({c: z[f"img_{c}"] for c in task.cameras}, z["proprio"])}
        if last is not None:
            acts = z["actions"]
            if len(acts) != t - last:
                note = f"; {f.name} does not follow step {last}, the episode ends before it"
                break
            grid = [int(s) - start for s in z["grid_steps"]]
            for i, s in enumerate(grid):
                add[s] = ({c: z[f"frame_img_{c}"][i] for c in task.cameras}, None)
            for s, q in zip(z["frame_steps"], z.get("frame_proprio", np.zeros((0, 0)))):
                views = add.get(int(s) - start, (None, None))[0]
                add[int(s) - start] = (views, q)
            actions.append(acts)
            executed += bool(z["executed_sent"])
        frames.update(add)
        last = t
    if last is None or last == 0:
        return None, f"{len(files)} boundary{'' if len(files) == 1 else ' files'}, no whole chunk{note}"
    T = last
    steps = list(range(0, T + 1, every)) + ([T] if T % every else [])
    acts = np.concatenate(actions).astype(np.float32)  # (T, A)
    known = {s: q for s, (_, q) in frames.items() if q is not None}
    proprio, q = [], known[0]
    for s in range(T + 1):  # (T+1, P): the proprio posted, held between the steps that carry one
        q = known.get(s, q)
        proprio.append(q)
    images = {c: np.stack([frames[s][0][c] for s in steps]) for c in task.cameras}  # (K, H, W, 3)
    prov = provenance(session=meta["session"], episode_seed=meta["episode_seed"], start_step=start,
                      started=meta["started"], ended_by=ended_by, chunks_with_executed_actions=executed,
                      recorded_by="wamplan serve --record",
                      proprio=f"posted at steps {sorted(known)}; the steps between repeat the last posted")
    robot = str(meta["session"]).split("/")[0]
    ep = EpisodeData.logged(task, int(meta["number"]), acts, np.stack(proprio), images, steps, image_every=every,
                            source=SOURCE_PREFIX + robot, outcome=outcome, provenance=prov)
    return ep, f"{T} steps, {len(steps)} frames{note}"


class Recorder:
    """Writes the proxy's sessions into the episode store ``root`` (see the module docstring). The proxy calls
    ``ran``/``frame`` when a request reports the chunk before it, ``boundary`` once it answered, ``end`` when a
    session is dropped or restarted, ``close`` on shutdown."""

    def __init__(self, root: str | Path, task: TaskSpec, cameras: tuple[str, ...], chunk: int,
                 every: int | None = None):
        self.root, self.task, self.chunk = check_record_dir(root), task, chunk
        self.root.mkdir(parents=True, exist_ok=True)
        self.every = every or chunk
        lacking = [c for c in task.cameras if c not in cameras]
        if lacking:
            raise UserError(f"--record: the requests carry no view of camera(s) {lacking} of task {task.name}, "
                            f"whose episodes hold every camera; record with a profile that maps them")
        try:
            self.store = EpisodeStore(self.root, create=True, env={"task": task.name}, image_every=self.every,
                                      task=task, provenance=provenance(recorded_by="wamplan serve --record"))
        except StoreError as e:
            raise UserError(f"--record {root}: {e}") from None
        self.journals = self.root / JOURNALS
        self.journals.mkdir(exist_ok=True)
        self._open: dict[Any, Journal] = {}
        self._lock = threading.Lock()
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="wamplan-record")
        self.recovered = self._recover()  # one line each: the journals a killed proxy left

    # ------------------------------------------------------------------ numbering
    def _next_number(self) -> int:
        used = [int(m.group(1)) for p in self.store.episode_paths() if (m := re.search(r"-s(\d+)$", p.stem))]
        used += [int(m.group(1)) for p in self.journals.iterdir() if (m := re.match(r"(\d+)-", p.name))]
        return max(used, default=-1) + 1

    # ------------------------------------------------------------------ what the proxy reports
    def ran(self, session: Any, actions: np.ndarray) -> None:
        """The actions the robot ran of the chunk answered last ((k, A), the task's columns)."""
        j = self._open.get(session)
        if j is not None:
            j.ran = np.array(actions, np.float32)

    def frame(self, session: Any, obs: Observation) -> None:
        """A frame the robot saw during the chunk answered last."""
        j = self._open.get(session)
        if j is not None:
            j.frames[obs.step] = obs

    def boundary(self, session: Any, obs: Observation, answered: np.ndarray, seed: int = 0) -> None:
        """Boundary ``obs`` answered with ``answered`` ((H, A), what the robot will run). A write that fails (a full
        disk) is logged; the robot's answer does not wait on it."""
        try:
            self._boundary(session, obs, answered, seed)
        except OSError:
            log.exception("recording session %s at step %d failed", session.key, obs.step)

    def _boundary(self, session: Any, obs: Observation, answered: np.ndarray, seed: int) -> None:
        with self._lock:
            j = self._open.get(session)
            if j is not None and (obs.step == 0 or j.gap(obs.step, self.every)):
                why = "new-episode" if obs.step == 0 else j.gap(obs.step, self.every)
                if obs.step:
                    log.warning("recording session %s: %s; episode %d ends at step %s and a new one starts at "
                                "step %d", session.key, why, j.number, j.last, obs.step)
                self._finish(j, "new-episode" if obs.step == 0 else f"gap: {why}")
                j = None
            if j is None:
                n = self._next_number()
                j = Journal(self.journals / f"{n:07d}-{source_tag(session.key)}", n, session.key, obs.step, seed,
                            self.chunk)
                self._open[session] = j
        with j.lock:
            if not j.closed:
                j.write_boundary(obs, answered, self.every)

    def end(self, session: Any, why: str) -> None:
        """The session's episode ended (it was dropped, restarted or evicted): write it."""
        with self._lock:
            j = self._open.get(session)
            if j is not None:
                self._finish(j, why)

    def close(self) -> None:
        """Write every episode in progress, and wait for the writes."""
        with self._lock:
            for j in list(self._open.values()):
                self._finish(j, "shutdown")
        self._writer.shutdown(wait=True)

    # ------------------------------------------------------------------ writing episodes
    def _finish(self, j: Journal, why: str) -> None:
        """(under ``_lock``) Close journal ``j`` and write its episode in the background."""
        self._open = {s: o for s, o in self._open.items() if o is not j}
        with j.lock:
            j.closed = True
        self._writer.submit(self._write, j.path, "logged", why, j)

    def _write(self, path: Path, outcome: str, why: str, journal: Journal | None = None) -> str:
        try:
            ep, found = build_episode(path, self.task, self.every, outcome, why)
            if ep is None:
                shutil.rmtree(path)
                return f"{path.name}: {found}; removed"
            final = self.store.episode_path(ep.source, ep.seed)
            if not final.exists():  # a killed proxy may have written it and not yet removed the journal
                self.store.write(ep)
            shutil.rmtree(path)
            return f"{path.name} -> {final.relative_to(self.root)} ({outcome}: {found})"
        except Exception as e:  # a recording must not take the proxy down; the journal stays for the next start
            log.exception("recording %s failed; its journal stays for the next `serve --record`", path)
            return f"{path.name}: not written ({reason(e)}); left in place"
        finally:
            if journal is not None:
                journal.release()

    def _recover(self) -> list[str]:
        """Finalise the journals a stopped proxy left (outcome ``interrupted``) -> one line each."""
        lines = []
        for path in sorted(p for p in self.journals.iterdir() if p.is_dir()):
            fd = os.open(path / LOCK, os.O_CREAT | os.O_RDWR, 0o644) if (path / META).is_file() else None
            try:
                if fd is None:
                    shutil.rmtree(path)
                    lines.append(f"{path.name}: no {META} (killed as it started); removed")
                    continue
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    lines.append(f"{path.name}: recorded by a proxy that still runs; left alone")
                    continue
                lines.append(self._write(path, "interrupted", "recovered: the proxy stopped mid-episode"))
            finally:
                if fd is not None:
                    os.close(fd)
        return lines
