"""``wamplan data alignment``: the cube's error to the hole while carried over the mount, from the stored poses."""

import json

import numpy as np

from wamplan.cli import main
from wamplan.data.alignment import episode_alignment

HOLE = np.array([0.0, 0.12, 0.025])
HALF = 0.02


def pose(x, y, z, yaw_deg):
    h = np.radians(yaw_deg) / 2
    return [x, y, z, np.cos(h), 0.0, 0.0, np.sin(h)]


def test_closest_pass_over_the_mount_is_reported():
    # the cube is carried in from 10 cm away, passes 3 mm from the axis (yaw 100 deg = 10 deg mod 90) above the
    # mount, then is dropped beside it (closer in xy, but below the mount's top: not "over the mount")
    cube = np.array([pose(0.1, 0.12, 0.08, 100), pose(0.02, 0.125, 0.08, 100), pose(0.003, 0.12, 0.06, 100),
                     pose(0.001, 0.12, 0.02, 0)])
    tcp = cube.copy()
    tcp[:, 0] -= 0.004  # grasped 4 mm off centre in x
    r = episode_alignment(cube, tcp, HOLE, HALF, source="s", seed=3, outcome="lifted_not_aligned")
    assert r.step == 2 and r.over_steps == 2
    assert np.isclose(r.xy_mm, 3.0) and np.isclose(r.dx_mm, 3.0) and np.isclose(r.dy_mm, 0.0, atol=1e-9)
    assert np.isclose(r.yaw_deg, 10.0) and np.isclose(r.in_hand_mm, 4.0)


def test_never_over_the_mount():
    cube = np.array([pose(0.1, 0.0, 0.02, 0), pose(0.05, 0.0, 0.02, 0)])  # on the table, never lifted
    r = episode_alignment(cube, cube, HOLE, HALF, source="s", seed=0, outcome="never_lifted")
    assert r.over_steps == 0 and r.yaw_deg is None and r.in_hand_mm is None
    assert r.step == 1 and np.isclose(r.xy_mm, 1e3 * np.hypot(0.05, 0.12))


def test_cli_on_expert_episodes(expert_store, capsys):
    assert main(["data", "alignment", str(expert_store), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["episodes"]) == 2 and set(out["summary"]) == {"success"}
    for e in out["episodes"]:  # the expert seats the cube: it passed within the task's 4 mm, square to the hole
        assert e["over_steps"] > 0 and e["xy_mm"] < 4.0 and abs(e["yaw_deg"]) < 5.7
    assert main(["data", "alignment", str(expert_store), "--quiet"]) == 0
    assert "success" in capsys.readouterr().out
