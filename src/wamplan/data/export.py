"""Export an episode store in the HDF5 layout Cosmos Policy's post-training reads (its RoboCasa loader).

    wamplan data export --format cosmos-policy DIR OUT

Layout written under ``OUT`` (the trainer finds ``*.hdf5`` files recursively under its data directories)::

    OUT/demos/wamplan_demos.hdf5            demonstrations (robomimic-style, RoboCasa camera names)
        data.attrs: total (steps in all demos), wamplan_* provenance (store, env, image_size, cameras)
        data/demo_<i>.attrs: task_description, num_samples (= N), wamplan_seed, wamplan_source, success, outcome
        data/demo_<i>/obs/robot0_agentview_left_rgb   (N, S, S, 3) uint8   the store's first camera (cube: front)
        data/demo_<i>/obs/robot0_agentview_right_rgb  (N, S, S, 3) uint8   its second (cube: side)
        data/demo_<i>/obs/robot0_eye_in_hand_rgb      (N, S, S, 3) uint8   its third, the wrist's (cube: wrist)
        data/demo_<i>/actions                         (N, A) float32
        data/demo_<i>/robot_states                    (N, P) float32  (the proprio; the loader's name)
    OUT/rollouts/<source>-s<seed>.hdf5      one on-policy episode per file, flat
        attrs: task_description, success, wamplan_seed, wamplan_source, outcome
        primary_images / secondary_images / wrist_images  (N, S, S, 3) uint8   the three cameras, in order
        actions (N, A) float32, proprio (N, P) float32

The layout has three views, two third-person ones and the wrist's: a store's task must have three cameras, in
that order (the cube task's front, side, wrist). The task description is the store's task's instruction unless
``instruction`` says otherwise.

Steps: Cosmos Policy's loaders treat every array index as one control step (the frame at t, the actions
t..t+chunk-1, the future frame at t+chunk), so every step needs its three views. A store keeps views only
every ``--image-every`` steps; exporting one collected with more than 1 is refused (re-collect with
``--image-every 1``): there is no sound way to fill the missing views, and re-chunking the actions to the
image cadence would change the action space the policy learns. An episode of T steps has T+1 frames
(steps 0..T, the last one showing the final state), so N = T+1 and the actions get one padding row at
step T: a no-op (zero motion, the last gripper command where the task has a gripper), which is also what the arm does once
the episode has ended. ``demo.attrs["wamplan_padded_actions"]`` = 1 records it.

Which file an episode goes to: with ``split="auto"`` successful expert episodes are demonstrations and
every other episode (other sources, failures) is a rollout file carrying its ``success`` flag, as the
trainer's value function expects (demos are scored with a terminal reward of 1).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from wamplan.config import check_numbers, field, require
from wamplan.data.store import IMAGE_COMPRESSION, EpisodeData, EpisodeStore, atomic_h5, source_tag
from wamplan.envs.spec import TaskSpec
from wamplan.errors import UserError

FORMATS = ("cosmos-policy",)
SPLITS = ("auto", "demos", "rollouts")
# the layout's views, in the order of a store's cameras: two third-person views, then the wrist's
DEMO_VIEWS = ("robot0_agentview_left_rgb", "robot0_agentview_right_rgb", "robot0_eye_in_hand_rgb")  # RoboCasa obs keys
ROLLOUT_VIEWS = ("primary_images", "secondary_images", "wrist_images")
DEMOS_FILE = "demos/wamplan_demos.hdf5"
ROLLOUTS_DIR = "rollouts"


def view_names(cameras: tuple[str, ...], views: tuple[str, ...]) -> dict[str, str]:
    """camera -> the layout's name of its view (``DEMO_VIEWS`` or ``ROLLOUT_VIEWS``), the cameras in order."""
    if len(cameras) != len(views):
        raise UserError(f"Cosmos Policy's layout holds {len(views)} views (two third-person, then the wrist's), but "
                        f"the store's task has the cameras {list(cameras)}; export a store of a three-camera task")
    return dict(zip(cameras, views))


@dataclass(frozen=True)
class CosmosExportConfig:
    """How a store becomes Cosmos Policy training files."""

    instruction: str = field("", "task_description written with every episode (default: the store's task's "
                                 "instruction)")
    image_size: int = field(224, "square size of the exported views (cosmos-policy: 224 by default, what Cosmos Policy "
                                 "trains at; lerobot: the store's by default); 0 keeps the store's")
    split: str = field("auto", "auto: successful expert episodes are demos, the rest rollouts; or demos / rollouts",
                       choices=SPLITS)
    sources: tuple[str, ...] = field((), "export only these sources (e.g. expert); empty: every episode")

    def __post_init__(self) -> None:
        check_numbers(self)
        require(self.instruction == "" or bool(self.instruction.strip()), "--instruction must not be blank")
        require(self.image_size >= 0, f"--image-size must be >= 0 (0 keeps the store's size), got {self.image_size}")
        require(self.split in SPLITS, f"--split must be one of {list(SPLITS)}, got '{self.split}'")


def resize_frames(frames: np.ndarray, size: int) -> np.ndarray:
    """(N, h, w, 3) uint8 -> (N, size, size, 3) uint8, bilinear with antialiasing (as the /act client's)."""
    if size == 0 or (frames.shape[1] == size and frames.shape[2] == size):
        return frames
    import torch
    import torch.nn.functional as F

    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float()  # (N, 3, h, w)
    y = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)  # (N, 3, s, s)
    return y.permute(0, 2, 3, 1).round().clamp(0, 255).to(torch.uint8).numpy()  # (N, s, s, 3)


def require_every_step(store: EpisodeStore, layout: str = "Cosmos Policy") -> None:
    """One line unless ``store`` keeps every step's views: ``layout`` (a format whose frames are control steps)
    needs them, and there is no sound way to fill the missing ones."""
    if store.image_every != 1:
        raise UserError(f"{store.root} stores views every {store.image_every} steps, but {layout} needs every "
                        f"step's views: re-collect with `wamplan collect ... --image-every 1`")


def require_empty(out: Path) -> None:
    """One line unless ``out`` is new or an empty directory: an export is not mixed into a checkpoint, a store,
    anything."""
    if out.exists() and not out.is_dir():
        raise UserError(f"{out} is a file; choose a new OUT directory")
    there = sorted(e.name for e in out.iterdir()) if out.is_dir() else []
    if there:
        raise UserError(f"{out} exists and is not empty ({', '.join(there[:3])}{', ...' if len(there) > 3 else ''}); "
                        f"choose a new or empty OUT directory")


def episode_arrays(ep: EpisodeData, image_size: int, task: TaskSpec, layout: str = "Cosmos Policy") -> dict[str, Any]:
    """One stored episode of ``task`` as per-step arrays (N = T+1 steps, the actions padded by one no-op row; see
    the module docstring), as Cosmos Policy's and LeRobot's layouts (``layout``, named in the refusal) hold them."""
    T = ep.length
    if not np.array_equal(ep.image_steps, np.arange(T + 1)):
        raise UserError(f"episode {ep.source} seed {ep.seed} has views at {len(ep.image_steps)} of its {T + 1} steps; "
                        f"{layout} needs every step's views: re-collect with `wamplan collect --image-every 1`")
    pad = np.zeros((1, ep.actions.shape[1]), np.float32)  # (1, A): no motion ...
    if (g := task.gripper_index) is not None:  # ... the last gripper command (open if none)
        pad[0, g] = ep.actions[-1, g] if T else task.gripper_open
    return dict(actions=np.concatenate([ep.actions.astype(np.float32), pad]),  # (T+1, A)
                proprio=ep.proprio.astype(np.float32),  # (T+1, P)
                images={c: resize_frames(ep.images[c], image_size) for c in task.cameras})  # (T+1, S, S, 3) each


def _meta(ep: EpisodeData) -> dict[str, Any]:
    return dict(wamplan_seed=int(ep.seed), wamplan_source=ep.source, success=bool(ep.success),
                outcome=ep.outcome, wamplan_padded_actions=1)


def _images(group: h5py.Group, names: dict[str, str], images: dict[str, np.ndarray]) -> None:
    for cam, name in names.items():
        arr = images[cam]  # (N, S, S, 3) uint8
        group.create_dataset(name, data=arr, chunks=(1, *arr.shape[1:]), **IMAGE_COMPRESSION)


def _is_demo(ep: EpisodeData, split: str) -> bool:
    return split == "demos" or (split == "auto" and ep.source == "expert" and ep.success)


def _episodes(store: EpisodeStore, paths: list[str]) -> Iterator[EpisodeData]:
    for p in paths:
        yield store.load(p)


def export_cosmos_policy(store_dir: str | Path, out_dir: str | Path, cfg: CosmosExportConfig) -> dict[str, Any]:
    """Write ``store_dir``'s episodes under ``out_dir`` (see the module docstring); returns a summary."""
    store = EpisodeStore(store_dir)
    task = store.task
    demo_views, rollout_views = view_names(store.cameras, DEMO_VIEWS), view_names(store.cameras, ROLLOUT_VIEWS)
    instruction = cfg.instruction or task.instruction
    require_every_step(store)
    paths = [m["path"] for m in store.iter_meta() if not cfg.sources or m["source"] in cfg.sources]
    if not paths:
        raise UserError(f"{store_dir} has no episode to export (sources {list(cfg.sources) or 'all'}); "
                        f"check --sources or the store")
    out = Path(out_dir)
    demos_path = out / DEMOS_FILE
    if demos_path.exists() or (out / ROLLOUTS_DIR).exists():
        raise UserError(f"{out} holds an export already; choose a new OUT directory or delete it")
    require_empty(out)
    (out / ROLLOUTS_DIR).mkdir(parents=True)
    demos_path.parent.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = dict(out=str(out), demos=0, demo_steps=0, rollouts=0, rollout_steps=0,
                                   image_size=cfg.image_size or None, files=[])
    with atomic_h5(demos_path) as f:
        data = f.create_group("data")
        for ep in _episodes(store, paths):
            arr = episode_arrays(ep, cfg.image_size, task)
            n = int(arr["actions"].shape[0])
            if _is_demo(ep, cfg.split):
                g = data.create_group(f"demo_{summary['demos']}")
                g.attrs.update(task_description=instruction, num_samples=n, **_meta(ep))
                _images(g.create_group("obs"), demo_views, arr["images"])
                g.create_dataset("actions", data=arr["actions"])
                g.create_dataset("robot_states", data=arr["proprio"])
                summary["demos"] += 1
                summary["demo_steps"] += n
            else:
                path = out / ROLLOUTS_DIR / f"{source_tag(ep.source)}-s{ep.seed:07d}.hdf5"
                with atomic_h5(path) as r:
                    r.attrs.update(task_description=instruction, **_meta(ep))
                    _images(r, rollout_views, arr["images"])
                    r.create_dataset("actions", data=arr["actions"])
                    r.create_dataset("proprio", data=arr["proprio"])
                summary["rollouts"] += 1
                summary["rollout_steps"] += n
                summary["files"].append(str(path))
        data.attrs.update(total=summary["demo_steps"], wamplan_store=str(Path(store_dir).resolve()),
                          wamplan_env=json.dumps(store.env), wamplan_image_size=cfg.image_size,
                          wamplan_cameras=json.dumps(demo_views))
    if summary["demos"] == 0:
        demos_path.unlink()  # the trainer reads every *.hdf5 it finds: leave no empty demo file behind
    else:
        summary["files"].insert(0, str(demos_path))
    return summary
