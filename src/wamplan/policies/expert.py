"""The scripted expert (privileged simulator state) and its noisy variant.

The expert is a state machine over the true cube, TCP and hole poses:

1. ``approach``: open, move 6 cm above the cube;
2. ``descend``: turn the fingers to the cube's yaw (mod 90°) while hovering, then go down to
   ``grasp_height`` above the cube's centre (12 mm: with tight clearance, fingers that reach lower
   jam against the hole's walls later);
3. ``close``: close the gripper for a few steps;
4. ``lift``: raise the cube well above the mount;
5. ``transport``: move the cube over the hole and turn it to the hole's yaw, using the cube's own
   pose (it can slip in the fingers);
6. ``insert``: descend at most ``insert_step`` metres per step, re-centring the cube over the hole;
   when the descent stalls (or the cube touches down), open the gripper;
7. ``retreat``: open and move up.

The phase is memory, but :meth:`ExpertPolicy.phase_for` reads the phase that fits a state from the state
alone (the grasp flag, the gripper width and the poses), using the same thresholds as the transitions
above; :meth:`ExpertPolicy.sync_to` puts the expert in that phase. The expert oracle re-synchronises at
every query, so its chunk is what the expert would do *from the current state*, whoever drove the robot
there (paper conditions 2-4).

Where the fingers turn (``turn_in``) decides what its demonstrations show a policy that imitates them from
pictures: "descend" (the default) turns while hovering above the cube, where the wrist camera sees it
large; "approach" turns from the first step, while moving.

Gains map metre/radian errors to normalised actions of the 5-D controller (pos 0.02 m, yaw 0.1 rad
per unit; see ``wamplan.envs.controller``).

It scripts the cube task: it acts in a task whose spec names it as the task's ``expert`` (cube-insertion).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from wamplan.config import check_numbers, field, require
from wamplan.envs.spec import Observation, TaskSpec
from wamplan.errors import UserError
from wamplan.policies.base import Policy, policy_task, register_policy

POS_BOUND, YAW_BOUND = 0.02, 0.1  # controller units (see wamplan.envs.controller)
TURN_PHASES = ("descend", "approach")
TURNED = 0.03  # rad: the fingers count as turned to the cube's yaw
HOVER_UNTIL = 0.1  # rad: turning above the cube, the fingers hold their height until within this of the cube's yaw


def quat_yaw(q: np.ndarray) -> float:
    w, x, y, z = q
    return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def wrap_quarter(a: float) -> float:
    return float((a + np.pi / 4) % (np.pi / 2) - np.pi / 4)


@dataclass(frozen=True)
class ExpertConfig:
    """Heights, step sizes, gain and tolerances of the expert's state machine (metres, radians)."""

    grasp_height: float = field(0.012, "TCP height above the cube centre when grasping, metres")
    hover: float = field(0.06, "height above the cube top before descending, metres")
    carry_clearance: float = field(0.035, "cube bottom clearance above the mount while carrying, metres")
    insert_step: float = field(0.003, "maximum descent per step while inserting, metres")
    close_steps: int = field(8, "steps the gripper closes before lifting")
    gain: float = field(1.0, "proportional gain on position errors (fraction of the error per step)")
    align_tol: float = field(0.003, "xy error over the hole below which insertion starts, metres")
    align_yaw_tol: float = field(0.05, "cube yaw error to the hole (mod 90°) below which insertion starts, radians")
    turn_in: str = field("descend", "phase in which the fingers turn to the cube's yaw: 'descend' (hovering "
                         "above the cube, where the wrist camera sees it, then down) or 'approach' (from the "
                         "first step, while moving)", choices=TURN_PHASES)

    def __post_init__(self):
        check_numbers(self)
        require(self.turn_in in TURN_PHASES, f"turn_in must be one of {list(TURN_PHASES)}, got {self.turn_in!r}")
        require(self.insert_step > 0, f"insert_step must be > 0, got {self.insert_step}")
        require(0 < self.gain <= 1.5, f"gain must be in (0, 1.5], got {self.gain}")
        require(self.align_tol > 0 and self.align_yaw_tol > 0,
                f"align_tol and align_yaw_tol must be > 0, got {self.align_tol}, {self.align_yaw_tol}")


def scripted_task(task: TaskSpec | None) -> TaskSpec:
    """The task the scripted expert acts in (default: the default policy task); one line for a task it does not
    script (whose spec names another ``expert``, or none)."""
    spec = policy_task(task)
    if spec.expert != ExpertPolicy.name:
        has = f"'{spec.expert}' as its expert" if spec.expert else "no scripted expert"
        raise UserError(f"the scripted expert acts in the tasks whose spec names it (cube-insertion); task "
                        f"'{spec.name}' has {has}; use --source pink, or import its demonstrations with `wamplan data import`")
    return spec


@register_policy("expert")
class ExpertPolicy(Policy):
    """Scripted expert; needs ``obs.state`` (privileged) and never images."""

    def __init__(self, config: ExpertConfig | None = None, task: TaskSpec | None = None):
        self.config = config or ExpertConfig()
        self.task = scripted_task(task)
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        self.phase = "approach"
        self.phase_steps = 0
        self.z_history: list[float] = []

    def config_dict(self) -> dict[str, Any]:
        from wamplan.config import to_dict

        return {"name": self.name, **to_dict(self.config)}

    def _goto(self, tcp: np.ndarray, target: np.ndarray, max_step: float = POS_BOUND) -> np.ndarray:
        d = (target - tcp) * self.config.gain  # (3,) metres
        n = np.linalg.norm(d)
        if n > max_step:
            d = d * (max_step / n)
        return d / POS_BOUND

    def phase_for(self, obs: Observation) -> str:
        """The phase that fits ``obs`` (privileged state + proprio), whatever happened before."""
        c, s = self.config, obs.state
        tcp, cube = s["tcp_pose"][:3], s["cube_pose"][:3]
        hole, h = s["hole_pos"], float(s["cube_half_size"])
        grasped, lifted, descended = (bool(s["stages"][i]) for i in (0, 1, 3))
        xy_hole = float(np.linalg.norm(hole[:2] - cube[:2]))
        if descended:  # the cube is in the hole: push it home while held, else let go and leave
            return "insert" if grasped else "retreat"
        grasp_point = np.array([cube[0], cube[1], cube[2] + c.grasp_height])
        at_grasp = np.linalg.norm(grasp_point[:2] - tcp[:2]) < 0.004 and abs(tcp[2] - grasp_point[2]) < 0.004
        open_width = 0.075  # the Panda's fingers open to 0.08 m; below this they are closing or closed
        if at_grasp and not lifted and not grasped and float(obs.proprio[0]) < open_width:
            return "close"  # closing on the cube that still stands on the table (held: lift it)
        if grasped:
            z_goal = hole[2] + c.carry_clearance + h + c.grasp_height  # carrying height of the TCP
            if xy_hole < 2 * c.align_tol and tcp[2] < z_goal - 0.005:
                return "insert"  # over the hole and already going down
            if xy_hole < c.align_tol and abs(wrap_quarter(quat_yaw(s["cube_pose"][3:]))) < c.align_yaw_tol:
                return "insert"
            return "transport" if tcp[2] > z_goal - 0.01 else "lift"
        above = tcp[2] < cube[2] + h + c.hover + 0.02  # at or below the hover height over the cube
        if np.linalg.norm(cube[:2] - tcp[:2]) < 0.004 and above:
            return "descend"
        return "approach"

    # (current, read from the state) pairs where the current phase still fits: the fingers already press the
    # cube while the expert finishes its closing count
    _STILL_FITS = {("close", "lift")}

    def sync_to(self, obs: Observation) -> None:
        """Continue from the phase that fits ``obs`` (counters restart; a phase that already fits is kept)."""
        phase = self.phase_for(obs)
        if phase != self.phase and (self.phase, phase) not in self._STILL_FITS:
            self._set(phase)

    def _set(self, phase: str) -> None:
        self.phase, self.phase_steps = phase, 0
        self.z_history = []

    def act(self, obs: Observation) -> np.ndarray:
        c, s = self.config, obs.state
        tcp, tq = s["tcp_pose"][:3], s["tcp_pose"][3:]
        cube, cq = s["cube_pose"][:3], s["cube_pose"][3:]
        hole, h = s["hole_pos"], float(s["cube_half_size"])
        self.phase_steps += 1
        grip = 1.0
        yaw_act = 0.0
        cube_yaw_err = wrap_quarter(quat_yaw(cq))  # cube yaw relative to the hole (yaw 0), mod 90°
        turn_above = c.turn_in == "descend"
        if self.phase in ("approach", "descend"):
            # Finger yaw must match the cube's (mod 90°); the TCP frame is flipped (z down), so yaw signs differ.
            finger_err = wrap_quarter(wrap_quarter(quat_yaw(cq)) - self._finger_yaw(tq))
        if self.phase == "approach":
            yaw_act = 0.0 if turn_above else finger_err
            target = np.array([cube[0], cube[1], cube[2] + h + c.hover])
            move = self._goto(tcp, target)
            if np.linalg.norm(target[:2] - tcp[:2]) < 0.004 and abs(yaw_act) < TURNED and abs(target[2] - tcp[2]) < 0.02:
                self._set("descend")
        elif self.phase == "descend":
            yaw_act = finger_err
            z = cube[2] + c.grasp_height
            if turn_above and abs(finger_err) >= HOVER_UNTIL:  # turn first, then go down
                z = max(tcp[2], z)
            target = np.array([cube[0], cube[1], z])
            move = self._goto(tcp, target, max_step=0.01)
            if abs(tcp[2] - target[2]) < 0.003 and np.linalg.norm(target[:2] - tcp[:2]) < 0.003 \
                    and (abs(finger_err) < TURNED or not turn_above):
                self._set("close")
        elif self.phase == "close":
            move, grip = np.zeros(3), -1.0
            if self.phase_steps >= c.close_steps:
                self._set("lift")
        elif self.phase == "lift":
            grip = -1.0
            z_goal = hole[2] + c.carry_clearance + h + c.grasp_height
            move = self._goto(tcp, np.array([tcp[0], tcp[1], z_goal]))
            if tcp[2] > z_goal - 0.01:
                self._set("transport")
        elif self.phase == "transport":
            grip = -1.0
            z_goal = hole[2] + c.carry_clearance + h + c.grasp_height
            # Move the cube (not the TCP) over the hole; the offset is how the cube sits in the hand.
            target = tcp + np.array([hole[0] - cube[0], hole[1] - cube[1], z_goal - tcp[2]])
            move = self._goto(tcp, target)
            yaw_act = -cube_yaw_err
            if np.linalg.norm(hole[:2] - cube[:2]) < c.align_tol and abs(cube_yaw_err) < c.align_yaw_tol:
                self._set("insert")
        elif self.phase == "insert":
            grip = -1.0
            xy = np.array([hole[0] - cube[0], hole[1] - cube[1]])
            dz = -c.insert_step if np.linalg.norm(xy) < 2 * c.align_tol else 0.0
            move = np.array([*(xy * c.gain), dz]) / POS_BOUND
            yaw_act = -cube_yaw_err
            self.z_history.append(float(tcp[2]))
            stalled = len(self.z_history) > 6 and self.z_history[-6] - self.z_history[-1] < 0.001
            if cube[2] - h < 0.002 or stalled:
                self._set("retreat")
        else:  # retreat
            move = np.array([0.0, 0.0, 0.5]) if self.phase_steps > 3 else np.zeros(3)
        a = np.concatenate([np.clip(move, -1, 1), [np.clip(yaw_act / YAW_BOUND, -1, 1)], [grip]])
        return a.astype(np.float32)

    @staticmethod
    def _finger_yaw(tq: np.ndarray) -> float:
        """Yaw of the gripper's closing axis (TCP y) in the world, mod 90°."""
        w, x, y, z = tq
        # second column of the rotation matrix: the TCP's y axis in world coordinates
        ry = np.array([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)])
        return wrap_quarter(float(np.arctan2(ry[1], ry[0])) - np.pi / 2)
