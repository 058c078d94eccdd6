"""A WAM's predicted views at each branch group's boundary, encoded: the target a planner ranks the siblings against.

    check_target_wam(wam, cameras, steps)           # one line when the WAM cannot give these stores' targets
    targets = group_targets(wam, groups, encoder)   # (G_total, V, N, D), groups: data.readers.BranchGroups

The WAM is queried on the group's boundary observation (the parent's stored images and proprio at the branch
step, which every sibling shares) with its default instruction, as the planned policy queries it at a chunk
boundary; its predicted views, in the stores' camera order, are encoded with the world model's frozen encoder.
"""

from __future__ import annotations

from typing import Sequence

import h5py
import numpy as np
import torch

from wamplan.envs.spec import Observation
from wamplan.errors import UserError
from wamplan.wam.base import WAM


def check_target_wam(wam: WAM, cameras: Sequence[str], steps: int, option: str = "--wam") -> None:
    """Refuse (one line naming ``option``) a WAM whose predicted views cannot be the targets of siblings scored
    ``steps`` steps after their boundary in views of ``cameras``: another chunk length, or a camera it does not
    predict."""
    if steps != wam.chunk_length:
        raise UserError(f"{option}: the siblings are scored {steps} steps after the boundary but the WAM predicts "
                        f"the views {wam.chunk_length} steps on; score them {wam.chunk_length} steps on (a horizon of "
                        f"chunk / frameskip frames) or use a WAM of that chunk length")
    missing = [c for c in cameras if c not in wam.cameras]
    if missing:
        raise UserError(f"{option}: the WAM predicts no view for the stores' cameras {missing}; use a WAM of this "
                        f"task")


def group_targets(wam: WAM, groups, encoder) -> torch.Tensor:
    """(G_total, V, N, D) float32: ``wam``'s predicted views of each of ``groups``' boundaries (a
    ``data.readers.BranchGroups``), in its camera order, encoded by ``encoder``."""
    out = []
    for members in groups.items:
        e = groups.episodes[members[0][0]]
        boundary, start = e.branch_at  # the parent's boundary, and its step at the branch's step 0
        k = list(e.image_steps).index(boundary - start)  # the stored frame at the boundary
        with h5py.File(e.path, "r") as f:
            obs = Observation(step=boundary, proprio=f["proprio"][boundary - start],
                              images={c: f["images"][c][k] for c in groups.cameras})
        pred = wam.predict(obs, wam.default_instruction)
        views = np.stack([pred.images[c] for c in groups.cameras])  # (V, H, W, 3) uint8
        out.append(encoder.encode(views).float().cpu())  # (V, N, D)
    return torch.stack(out) if out else torch.zeros(0)
