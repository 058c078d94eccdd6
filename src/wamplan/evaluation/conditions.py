"""The paper's seven evaluation conditions (§4, Table 1): which dynamics, seed and target each uses."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Condition:
    id: int
    dynamics: str  # none | simulator | learned-plain | learned-augmented
    seed: str  # wam | expert  (who proposes the chunk that initialises the search)
    target: str  # wam | expert | none  (whose predicted t+H views the search aims at)

    @property
    def learned(self) -> bool:
        """Plans in a learned world model (conditions 6 and 7)."""
        return self.dynamics.startswith("learned")

    @property
    def label(self) -> str:
        dyn = {"none": "None (open loop)", "simulator": "Simulator", "learned-plain": "Learned WM",
               "learned-augmented": "Augmented WM"}[self.dynamics]
        return dyn


CONDITIONS: dict[int, Condition] = {c.id: c for c in (
    Condition(1, "none", "wam", "none"),
    Condition(2, "simulator", "expert", "expert"),
    Condition(3, "simulator", "expert", "wam"),
    Condition(4, "simulator", "wam", "expert"),
    Condition(5, "simulator", "wam", "wam"),
    Condition(6, "learned-plain", "wam", "wam"),
    Condition(7, "learned-augmented", "wam", "wam"),
)}


def parse_conditions(spec: str) -> list[int]:
    """'1,6,7' or '1-7' -> [1, 6, 7]; a malformed, backward or empty list and unknown ids are a one-line error."""
    from wamplan.config import int_list
    from wamplan.errors import UserError

    ids = int_list(spec, "--conditions", example="1,6,7 or 1-7")
    bad = sorted({i for i in ids if i not in CONDITIONS})
    if bad:
        raise UserError(f"--conditions '{spec}': unknown condition(s) {bad}; the paper's are 1-7")
    return sorted(set(ids))
