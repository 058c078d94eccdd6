"""`wamplan eval` builds its nested EvalConfig from planner options generated from the planner registry:
a planner registered in planning/ appears in `eval` with no edit to the evaluation code."""

from __future__ import annotations

import json
import re
from pathlib import Path
from dataclasses import dataclass

import pytest
import torch

from wamplan.cli import build_parser, main
from wamplan.config import ConfigError, field, require
from wamplan.errors import UserError
from wamplan.cli.eval_options import eval_config_from_args
from wamplan.evaluation.config import EvalConfig
from wamplan.evaluation.runner import _check_same_settings
from wamplan.planning import PLANNERS, CEMConfig, CostConfig, MPPIConfig, PlanResult, Planner, register_planner
from wamplan.planning.policy import PlannedPolicyConfig
from wamplan.planning.configs import PLANNER_CONFIGS
from wamplan.planning.defaults import WamplanConfig


@dataclass(frozen=True)
class ToyConfig:
    shift: float = field(0.5, "how far the toy planner moves every action")
    temperature: int = field(3, "an int here, a float in MPPI: offered per planner as --toy-temperature")

    def __post_init__(self):
        require(self.shift >= 0, f"shift must be >= 0, got {self.shift}")


@pytest.fixture
def toy_planner():
    @register_planner("toy")
    class ToyPlanner(Planner):
        config_cls = ToyConfig

        def plan(self, seed_actions, objective, *, generator=None, seed=None) -> PlanResult:
            a = seed_actions + self.config.shift  # (H, A)
            return PlanResult(a, a, torch.zeros_like(a), a, float(objective(a[None])[0]), [], 1)

    yield ToyPlanner
    PLANNERS.pop("toy")
    PLANNER_CONFIGS.pop("toy")


def _cfg(*argv: str) -> EvalConfig:
    return eval_config_from_args(build_parser().parse_args(["eval", "--out", "x", *argv]))


def test_a_registered_planner_appears_in_eval_with_its_options(toy_planner, capsys):
    cfg = _cfg("--planner", "toy", "--shift", "0.25", "--toy-temperature", "7")
    assert cfg.planner == "toy" and cfg.planner_config == ToyConfig(shift=0.25, temperature=7)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["eval", "--help-all"])
    out = capsys.readouterr().out
    assert "--planner {cem,cem-gripper,mppi,toy,wamplan}" in out and "--shift SHIFT" in out and "[toy]" in out
    assert "--toy-temperature" in out and "--mppi-temperature" in out  # the clash is spelled per planner
    with pytest.raises(ConfigError, match="shift must be >= 0"):
        _cfg("--planner", "toy", "--shift", "-1")
    assert EvalConfig(planner="toy", planner_config={"shift": 2.0}).planner_config == ToyConfig(shift=2.0)


def test_every_planner_cost_and_policy_option_reaches_the_nested_config():
    cfg = _cfg("--planner", "mppi", "--temperature", "0.3", "--momentum", "0.5", "--no-update-std",
               "--min-std", "0.01", "--num-optimized", "15", "--init-std-per-dim", "0.1", "0.1", "0.1", "0.1", "0",
               "--cost-name", "cls", "--cost-view-weights", "0", "0", "1", "--first-chunk", "rest-history",
               "--plan-seed", "3", "--camera-size", "64", "--max-steps", "40")
    assert cfg.planner_config == MPPIConfig(temperature=0.3, momentum=0.5, update_std=False, min_std=0.01,
                                            num_optimized=15, init_std_per_dim=(0.1, 0.1, 0.1, 0.1, 0.0))
    assert cfg.cost == CostConfig(name="cls", view_weights=(0.0, 0.0, 1.0))
    assert cfg.policy == PlannedPolicyConfig(first_chunk="rest-history", plan_seed=3)
    assert (cfg.env.camera_size, cfg.env.max_episode_steps) == (64, 40)
    assert _cfg("--planner", "cem", "--num-elites", "4", "--std-ddof", "1").planner_config == \
        CEMConfig(num_elites=4, std_ddof=1)
    assert _cfg().planner_config == WamplanConfig() and _cfg().planner == "wamplan"  # wamplan's default planner
    assert _cfg("--temperature", "0.5").planner_config == WamplanConfig(temperature=0.5)


def test_an_option_of_another_planner_is_refused_in_one_line(capsys):
    with pytest.raises(UserError, match=r"--temperature is an option of planner\(s\) \['mppi', 'wamplan'\], "
                                        r"not of 'cem'"):
        _cfg("--planner", "cem", "--temperature", "0.3")
    assert main(["eval", "--out", "x", "--planner", "mppi", "--num-elites", "4", "--wam", "w"]) == 2
    assert "--num-elites is an option of planner(s) ['cem', 'cem-gripper'], not of 'mppi'" in capsys.readouterr().err
    # a bad value is named by the option that set it, not the config's field (the API's ConfigError names the field)
    with pytest.raises(ConfigError, match=r"^--num-elites must be in \[1, --num-candidates=32\], got 99; lower "
                                          r"--num-elites or raise --num-candidates$"):
        _cfg("--planner", "cem", "--num-elites", "99")
    with pytest.raises(ConfigError, match=r"^num_elites must be in"):
        CEMConfig(num_elites=99)
    with pytest.raises(UserError, match="unknown planner 'nope'"):
        EvalConfig(planner="nope")
    with pytest.raises(ConfigError, match="needs a MPPIConfig"):
        EvalConfig(planner="mppi", planner_config=CEMConfig())


def test_one_directory_holds_one_nested_configuration(tmp_path):
    base = _cfg("--planner", "mppi", "--temperature", "0.3")
    _check_same_settings(tmp_path, base)
    stored = json.loads((tmp_path / "eval_config.json").read_text())
    assert stored["planner"] == "mppi" and stored["planner_config.temperature"] == 0.3
    assert "policy.first_chunk" not in stored and "device" not in stored
    _check_same_settings(tmp_path, _cfg("--planner", "mppi", "--temperature", "0.3", "--first-chunk", "rest-history"))
    for other in (("--planner", "mppi", "--temperature", "0.2"),
                  ("--planner", "mppi", "--temperature", "0.3", "--cost-name", "cls")):
        with pytest.raises(UserError, match="other settings"):
            _check_same_settings(tmp_path, _cfg(*other))
    with pytest.raises(UserError, match="holds an evaluation with --planner mppi"):
        _check_same_settings(tmp_path, _cfg("--planner", "cem"))


def test_the_world_models_arithmetic_is_a_setting_of_the_directory(tmp_path, capsys):
    assert _cfg().wm_dtype == "float32" and _cfg("--wm-dtype", "bfloat16").wm_dtype == "bfloat16"
    with pytest.raises(ConfigError, match="wm_dtype 'float16' is not one of float32, bfloat16"):
        EvalConfig(wm_dtype="float16")
    with pytest.raises(SystemExit):
        _cfg("--wm-dtype", "float16")
    assert "invalid choice: 'float16'" in capsys.readouterr().err
    _check_same_settings(tmp_path, _cfg())
    stored = json.loads((tmp_path / "eval_config.json").read_text())
    del stored["wm_dtype"]  # a directory from before the setting: it ran in float32
    (tmp_path / "eval_config.json").write_text(json.dumps(stored))
    _check_same_settings(tmp_path, _cfg())
    with pytest.raises(UserError, match="wm_dtype"):
        _check_same_settings(tmp_path, _cfg("--wm-dtype", "bfloat16"))


def test_the_world_models_arithmetic_reaches_the_models_the_runs_plan_in(tmp_path):
    """`wamplan eval --wm-dtype bfloat16` runs with that setting, and it is the dtype of the world models its
    workers load for conditions 6 and 7 (and the one the API's planned policy loads); their encoders stay float32."""
    from pathlib import Path

    from wamplan.evaluation.records import append_record
    from wamplan.evaluation.runner import EvalWorker
    from wamplan.planning.build import plan_in_world_model

    mini = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"
    argv = ["--wm-dtype", "bfloat16", "--wam", str(mini / "tinywam"), "--wm-plain", str(mini / "wm_plain"),
            "--wm-augmented", str(mini / "wm_augmented"), "--camera-size", "64"]
    out = tmp_path / "eval"
    out.mkdir()
    append_record(out, dict(condition=6, seed=0, variant="open-loop", success=True, outcome="success"))
    assert main(["eval", "--conditions", "6", "--episodes", "1", "--out", str(out), *argv]) == 0  # nothing left to run
    assert json.loads((out / "eval_config.json").read_text())["wm_dtype"] == "bfloat16"  # the settings it ran with
    cfg = eval_config_from_args(build_parser().parse_args(["eval", "--out", str(out), *argv]))
    worker = EvalWorker(cfg)
    try:
        for cid in (6, 7):
            policy = worker.policy(cid)
            assert policy.dynamics.dtype == torch.bfloat16, cid
            assert next(policy.encoder.parameters(), torch.zeros(1)).dtype == torch.float32
    finally:
        worker.env.close()
    for c, dtype in ((cfg, torch.bfloat16), (_cfg(), torch.float32)):
        policy = plan_in_world_model(str(mini / "tinywam"), str(mini / "wm_plain"), c.planning, c.device, c.wm_dtype)
        assert policy.dynamics.dtype == dtype


def test_a_directory_from_before_a_new_setting_resumes_at_its_default(tmp_path):
    """A setting added after a directory was written (here the planner's min_std) does not block resuming
    it when requested at its default, which is what the older version ran with; another value still does."""
    _check_same_settings(tmp_path, _cfg())
    path = tmp_path / "eval_config.json"
    stored = json.loads(path.read_text())
    del stored["planner_config.min_std"], stored["policy.accept_margin"]
    for other in ((), ("--min-std", "0.01"), ("--accept-margin", "0.5")):
        path.write_text(json.dumps(stored))  # the old directory, as written before the two settings existed
        if not other:
            _check_same_settings(tmp_path, _cfg())
            continue
        with pytest.raises(UserError, match="other settings"):
            _check_same_settings(tmp_path, _cfg(*other))


def test_a_directory_from_before_an_option_left_resumes_only_if_it_ran_what_runs_now(tmp_path):
    """Options that left wamplan (they measured no gain), stored by an older version: at the value that ran what
    runs now the directory resumes (and forgets them); at another value it is refused in one line naming the option."""
    _check_same_settings(tmp_path, _cfg())
    path = tmp_path / "eval_config.json"
    stored = json.loads(path.read_text())
    retired = {"planner_config.noise_beta": 0.0, "policy.gate_above": None, "policy.rank_gate": None,
               "policy.replan_every": None, "policy.bias_correction": 0.0, "policy.correction_gain": 1.0,
               "cost.foreground": "", "cost.background_weight": 0.1, "cost.state_weight": 0.0,
               "policy.disagreement_weight": 0.0}
    path.write_text(json.dumps({**stored, **retired}))
    _check_same_settings(tmp_path, _cfg())
    assert json.loads(path.read_text()) == stored
    path.write_text(json.dumps({**stored, **retired, "policy.correction_gain": 0.5}))
    with pytest.raises(UserError, match="--correction-gain 0.5, an option wamplan no longer has"):
        _check_same_settings(tmp_path, _cfg())
    path.write_text(json.dumps({**stored, **retired, "cost.foreground": "runs/fg"}))
    with pytest.raises(UserError, match="--cost-foreground runs/fg, an option wamplan no longer has"):
        _check_same_settings(tmp_path, _cfg())
    path.write_text(json.dumps({**stored, **retired, "cost.state_weight": 0.3}))
    with pytest.raises(UserError, match="--cost-state-weight 0.3, an option wamplan no longer has"):
        _check_same_settings(tmp_path, _cfg())
    path.write_text(json.dumps({**stored, **retired, "policy.disagreement_weight": 1.0}))
    with pytest.raises(UserError, match="--disagreement-weight 1.0, an option wamplan no longer has"):
        _check_same_settings(tmp_path, _cfg())


def test_a_directory_of_another_planner_names_the_flag_that_resumes_it(tmp_path):
    """Directories written when CEM was the default ran it; the new default refuses them in one line that
    names --planner cem, which resumes them."""
    _check_same_settings(tmp_path, _cfg("--planner", "cem"))
    with pytest.raises(UserError, match=r"holds an evaluation with --planner cem .* add --planner cem to resume it"):
        _check_same_settings(tmp_path, _cfg())
    _check_same_settings(tmp_path, _cfg("--planner", "cem"))
    assert json.loads((tmp_path / "eval_config.json").read_text())["planner"] == "cem"


def test_a_served_wam_is_chosen_with_url_and_profile(tmp_path):
    cfg = _cfg("--wam-url", "http://127.0.0.1:8777/act", "--wam-profile", "cosmos-robocasa")
    assert (cfg.wam, cfg.wam_url, cfg.wam_profile) == ("", "http://127.0.0.1:8777/act", "cosmos-robocasa")
    cfg.check_for([1])
    with pytest.raises(SystemExit):  # argparse refuses a profile that does not exist and lists those that do
        _cfg("--wam-url", "http://h:1/act", "--wam-profile", "cosmos-libero")
    # another task: the client maps its cameras by position; the profiles name the cube's cameras
    _cfg("--wam-url", "http://127.0.0.1:8777/act", "--task", "peg-insertion-side").check_for([1])
    _cfg("--wam-url", "http://127.0.0.1:8777/act", "--wam-profile", "cosmos-aloha",
         "--task", "push-cube").check_for([1])
    with pytest.raises(UserError, match="--wam-profile cosmos-robocasa names cube-insertion's cameras.*leave it out"):
        _cfg("--wam-url", "http://127.0.0.1:8777/act", "--wam-profile", "cosmos-robocasa",
             "--task", "peg-insertion-side").check_for([1])
    for argv, match in ((("--wam-url", "h:1/act"), "http"),
                        (("--wam", str(tmp_path), "--wam-url", "http://h:1/act"), "only one of"),
                        ((), "--wam CKPT is required.*--wam-url"),
                        (("--wam", str(tmp_path), "--wam-profile", "cosmos-aloha"), "needs --wam-url")):
        with pytest.raises(UserError, match=match):
            _cfg(*argv).check_for([1])
    # the served WAM is part of a directory's settings; a directory from before the option keeps its own
    _check_same_settings(tmp_path, cfg)
    stored = json.loads((tmp_path / "eval_config.json").read_text())
    assert (stored["wam_url"], stored["wam_profile"], stored["wam"]) == (cfg.wam_url, "cosmos-robocasa", "")
    with pytest.raises(UserError, match="other settings.*wam_profile"):
        _check_same_settings(tmp_path, _cfg("--wam-url", cfg.wam_url, "--wam-profile", "cosmos-aloha"))
    old = tmp_path / "old"
    old.mkdir()
    _check_same_settings(old, _cfg("--wam", "ckpt"))
    assert "wam_url" not in json.loads((old / "eval_config.json").read_text())


def test_eval_plans_with_a_served_wam_through_a_profile(tmp_path, capsys):
    """Condition 1 (the WAM alone) for one short episode against a server with RoboCasa field names."""
    import numpy as np

    from wamplan.evaluation.records import read_records
    from wamplan.wam import WAM, WAMOutput
    from wamplan.serving.runner import BackgroundServer
    from wamplan.wam.server import create_app

    class HoldWAM(WAM):
        name = "test-hold"

        def __init__(self):
            self.seen: list[tuple] = []

        def predict(self, obs, instruction):
            self.seen.append((obs.proprio.shape, {c: im.shape for c, im in obs.images.items()}, instruction))
            actions = np.zeros((16, 5), np.float32)
            actions[:, 4] = 1.0  # keep the gripper open, do not move
            return WAMOutput(actions=actions, images=dict(obs.images))

    wam = HoldWAM()
    rmap = {"primary_image": "front", "secondary_image": "side", "wrist_image": "wrist"}
    resp = {"front": "future_image", "side": "future_image2", "wrist": "future_wrist_image"}
    with BackgroundServer(create_app(wam, request_map=rmap, response_map=resp)) as srv:
        assert main(["eval", "--out", str(tmp_path), "--conditions", "1", "--episodes", "1", "--max-steps", "20",
                     "--camera-size", "64", "--wam-url", srv.url + "/act", "--wam-profile", "cosmos-robocasa"]) == 0
    (rec,) = read_records(tmp_path)
    assert (rec["condition"], rec["seed"], rec["length"]) == (1, 0, 20)
    assert wam.seen[0] == ((10,), {c: (224, 224, 3) for c in ("front", "side", "wrist")},
                           "insert the cube into the square hole")
    assert len(wam.seen) == 2  # steps 0 and 16: one query per 16-step chunk


def test_a_missing_checkpoint_is_named_with_its_flag_and_fix(tmp_path):
    """The world model must exist; a missing one (an empty one included) is named with its flag."""
    ok = str(tmp_path)
    with pytest.raises(UserError, match=r"^--wm-augmented .*gone does not exist; train it or fix the path$"):
        _cfg("--wam", ok, "--wm-augmented", str(tmp_path / "gone")).check_for([7])
    with pytest.raises(UserError, match=r"^condition 7 needs --wm-augmented CKPT"):
        _cfg("--wam", ok).check_for([7])
    with pytest.raises(UserError, match=r"^--wam .*nowhere does not exist; train one with `wamplan wam train`"):
        _cfg("--wam", str(tmp_path / "nowhere")).check_for([1])
    _cfg("--wam", ok, "--wm-augmented", ok).check_for([1, 7])  # there: no error
    assert _cfg("--wm-augmented", ok).world_model(7) == ok and _cfg("--wm-augmented", ok).world_model(1) == ""


def test_several_world_models_joined_by_plus_or_commas_are_refused_but_a_path_holding_them_is_one(tmp_path):
    """An ensemble (A+B, A,B) left the core: refused in one line naming the fix, where its pieces are checkpoints;
    a path may hold a + or a comma, and then it is one checkpoint."""
    from wamplan.config import joined_checkpoints

    a, b = tmp_path / "wm_a", tmp_path / "wm_b"
    for d in (a, b):
        d.mkdir()
        (d / "config.json").write_text("{}")
    for spec in (f"{a}+{b}", f"{a},{b}", f"{a},{b}+{a}"):
        with pytest.raises(UserError, match=rf"^--wm-augmented {re.escape(spec)} joins \d world models into an "
                                            rf"ensemble, which wamplan no longer plans in .* pass one checkpoint, "
                                            rf"e\.g\. --wm-augmented {re.escape(str(a))}$"):
            _cfg("--wam", str(a), "--wm-augmented", spec).check_for([7])
    for name in ("exp+v2", "exp,v2"):  # an existing path with a + or a comma in it is one checkpoint
        one = tmp_path / name
        one.mkdir()
        assert _cfg("--wm-augmented", str(one)).world_model(7) == str(one)
        _cfg("--wam", str(a), "--wm-augmented", str(one)).check_for([7])
    assert joined_checkpoints(f"{a}+{tmp_path / 'gone'}") == []  # not all checkpoints: one path, and missing
    with pytest.raises(UserError, match=r"^--wm-augmented .*wm_a\+.*gone does not exist"):
        _cfg("--wam", str(a), "--wm-augmented", f"{a}+{tmp_path / 'gone'}").check_for([7])
    plain = tmp_path / "plain"  # a directory that is not a checkpoint is not a piece of an ensemble
    plain.mkdir()
    assert joined_checkpoints(f"{a}+{plain}") == [] and joined_checkpoints(f"{a}+") == []
    assert joined_checkpoints(f"{a}+{b}") == [str(a), str(b)]


def test_progress_bars_refresh_rarely_when_written_to_a_log(tmp_path):
    import io

    from wamplan.progress import LOG_MININTERVAL_S, progress_bar

    with open(tmp_path / "job.log", "w") as log:  # a redirected stream is no terminal
        assert progress_bar(total=1, file=log).mininterval == LOG_MININTERVAL_S
        assert progress_bar(total=1, file=log, mininterval=2).mininterval == 2  # an explicit setting wins

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    assert progress_bar(total=1, file=Terminal()).mininterval == 0.1  # tqdm's own default on a terminal


# ------------------------------------------------------------------ the task (--task)
@pytest.fixture
def gripperless_task():
    """A registered task without a gripper (and without a scripted expert), removed afterwards."""
    from wamplan.envs.maniskill import maniskill_task
    from wamplan.envs.spec import TASKS, register_task

    spec = register_task(maniskill_task("Toy-v1", name="toy-no-gripper", cameras=("base_camera",), action_dim=6,
                                        proprio_dim=13, max_episode_steps=20, instruction="", gripper_index=None))
    yield spec
    TASKS.pop(spec.name)


def test_the_task_reaches_the_env_and_the_planner(gripperless_task):
    cfg = _cfg("--task", "peg-insertion-side", "--planner", "cem-gripper", "--wam", "w")
    assert cfg.env.task == "peg-insertion-side" and cfg.planner_config.gripper_dim is None  # left to the task
    assert cfg.task_planner_config.gripper_dim == 6  # the peg task's gripper entry
    from wamplan.evaluation.runner import settings

    stored = settings(_cfg("--planner", "cem-gripper"))  # what the directory records: as it ran
    assert (stored["env.task"], stored["env.max_episode_steps"], stored["planner_config.gripper_dim"]) == \
        ("cube-insertion", 300, 4)
    with pytest.raises(UserError, match=r"unknown task 'nope'; choose one of \[.*'push-cube'"):  # after parsing
        _cfg("--task", "nope")
    with pytest.raises(UserError, match="task 'toy-no-gripper' has no gripper; use --planner cem"):
        _cfg("--task", "toy-no-gripper", "--planner", "cem-gripper", "--wam", "w").check_for([5])
    with pytest.raises(UserError, match=r"conditions \[2, 4\] seed or aim the search with the scripted expert, but "
                                        r"task 'toy-no-gripper' has none"):
        _cfg("--task", "toy-no-gripper", "--wam", "w").check_for([1, 2, 4, 5])


def test_a_directory_from_before_tasks_resumes_as_the_cube_task(tmp_path):
    """Directories written before --task recorded no task and their episode length as a number: they resume."""
    _check_same_settings(tmp_path, _cfg("--planner", "cem-gripper"))
    path = tmp_path / "eval_config.json"
    stored = json.loads(path.read_text())
    del stored["env.task"]
    path.write_text(json.dumps(stored))
    _check_same_settings(tmp_path, _cfg("--planner", "cem-gripper"))
    with pytest.raises(UserError, match="other settings.*env.task"):
        _check_same_settings(tmp_path, _cfg("--planner", "cem-gripper", "--task", "peg-insertion-side"))


def test_eval_refuses_a_wam_of_another_task_before_it_stores_its_settings(tmp_path, capsys):
    from types import SimpleNamespace

    from wamplan.envs.spec import get_task
    from wamplan.evaluation.runner import check_wam_task, check_world_model_task

    cfg = _cfg("--task", "push-cube", "--wam", "w")
    with pytest.raises(UserError, match="WAM w was made for task 'cube-insertion', but this run uses task "
                                        "'push-cube'; pass --task cube-insertion"):
        check_wam_task(cfg, SimpleNamespace(task=get_task("cube-insertion")))
    with pytest.raises(UserError, match="world-model checkpoint m was made for task 'cube-insertion'"):
        check_world_model_task(cfg, "m", SimpleNamespace(task=get_task("cube-insertion")))
    check_world_model_task(cfg, "m", SimpleNamespace(task=None))  # a model that records no task is not checked
    wam = "checkpoints/mini/tinywam"  # the shipped TinyWAM: made before tasks, so for cube-insertion
    assert main(["eval", "--conditions", "1", "--episodes", "1", "--out", str(tmp_path), "--wam", wam,
                 "--task", "push-cube"]) == 2
    assert f"WAM {wam} was made for task 'cube-insertion'" in capsys.readouterr().err
    assert not (tmp_path / "eval_config.json").exists()


def test_every_command_that_makes_an_env_takes_the_task(capsys):
    from wamplan.cli.main import iter_commands

    # the commands offering EnvConfig's generated options (--clearance is one) offer --task with them
    env_commands = [p.prog for p in iter_commands() if "--clearance" in p._option_string_actions]
    assert {"wamplan eval", "wamplan collect", "wamplan env rollout", "wamplan env render"} <= set(env_commands)
    assert all("--task" in p._option_string_actions for p in iter_commands()
               if p.prog in env_commands or p.prog in ("wamplan reproduce", "wamplan env check"))
    assert main(["tasks"]) == 0
    lines = capsys.readouterr().out.splitlines()
    from wamplan.envs.spec import TASKS

    assert len(lines) == len(TASKS) and [line.split()[0] for line in lines] == sorted(TASKS)
    cube = next(line for line in lines if line.startswith("cube-insertion "))
    assert "env CubeInsertion-v1" in cube and "cameras front,side,wrist" in cube and "action 5" in cube
    assert "proprio 10" in cube and "controller pd_ee_delta_xyzyaw" in cube and "episode 300 steps" in cube
    assert "demonstrations scripted expert (policy 'expert')" in cube
    peg = next(line for line in lines if line.startswith("peg-insertion-side "))
    assert "demonstrations maniskill-motion-planning" in peg


def test_a_directory_refuses_another_world_model_and_accepts_one_added_later(tmp_path):
    """A world model is a setting of the directory: one given for the first time joins it (its conditions had not
    run), the same checkpoint spelled another way resumes it, and another checkpoint in its place is refused."""
    from wamplan.evaluation.runner import run_evaluation

    out, a, b = tmp_path / "eval", tmp_path / "wm_a", tmp_path / "wm_b"
    for d in (a, b):
        d.mkdir()

    def resume(*argv: str) -> None:  # the run's checks, with every job done (no seeds): nothing is loaded
        run_evaluation(_cfg(*argv), [6, 7], [], out)

    resume("--wm-plain", str(a))
    from wamplan.evaluation.records import append_record

    append_record(out, dict(condition=6, seed=0, variant="plain", success=False, outcome="failure", length=10))
    resume("--wm-plain", str(a), "--wm-augmented", str(b))  # added: stored beside it (condition 7 has not run)
    assert json.loads((out / "eval_config.json").read_text())["wm_augmented"] == str(b)
    (tmp_path / "link_a").symlink_to(a)
    resume("--wm-plain", str(tmp_path / "link_a"))  # the same model; the augmented one stays stored
    for plain, augmented in ((b, b), (a, a)):
        with pytest.raises(UserError, match="other settings") as e:
            resume("--wm-plain", str(plain), "--wm-augmented", str(augmented))
        assert str(plain) in str(e.value)  # the changed setting, as requested
    ensemble = tmp_path / "ensemble"  # a directory an older version ran with an ensemble (A,B or A+B): refused
    for d in (a, b):
        (d / "config.json").write_text("{}")
    for spec in (f"{a},{b}", f"{a}+{b}"):
        run_evaluation(_cfg("--wm-augmented", str(a)), [7], [], ensemble)
        append_record(ensemble, dict(condition=7, seed=0, variant="open-loop", success=False, outcome="failure",
                                     length=9))
        stored = json.loads((ensemble / "eval_config.json").read_text())
        (ensemble / "eval_config.json").write_text(json.dumps({**stored, "wm_augmented": spec}))
        with pytest.raises(UserError, match=rf"^{re.escape(str(ensemble))} holds an evaluation run with "
                                            rf"--wm-augmented {re.escape(spec)}, an ensemble of world models, which "
                                            rf"wamplan no longer plans in"):
            run_evaluation(_cfg("--wm-augmented", str(a)), [7], [], ensemble)
        with pytest.raises(UserError, match="an ensemble of world models"):
            run_evaluation(_cfg(), [1], [], ensemble)  # whatever runs now
        (ensemble / "eval_config.json").unlink()
        (ensemble / "records.jsonl").unlink()


@pytest.mark.parametrize("argv", [
    ["--conditions", "9"],
    ["--episodes", "0"],
    [],  # no --wam
    ["--wam", "no/such/ckpt"],
    ["--num-elites", "3"],  # an option of another planner
    ["--planner", "cem", "--num-elites", "99"],  # a config that refuses its values
    ["--cost-name", "nope"],
    ["--wam", "checkpoints/mini/tinywam", "--cost-view-weights", "1", "1"],
    ["--wam", "checkpoints/mini/tinywam", "--num-optimized", "20"],  # more steps than the task's chunk
    ["--wam", "checkpoints/mini/tinywam", "--wam-send-chunk-frames", "4"],  # frames go to a served WAM only
])
def test_eval_refuses_bad_arguments_before_torch_loads(argv, tmp_path):
    """An argument error is answered from the settings alone: torch (seconds to import) is not loaded first."""
    import subprocess
    import sys

    code = ("import sys\nfrom wamplan.cli.main import main\n"
            "try:\n    rc = main(sys.argv[1:])\nexcept SystemExit as e:\n    rc = e.code\n"
            "print('torch' in sys.modules, rc)")
    run = subprocess.run([sys.executable, "-c", code, "eval", "--out", str(tmp_path / "run"), "--conditions", "1,7",
                          "--wm-augmented", "checkpoints/mini/wm_augmented", *argv],
                         cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=120)
    assert run.stdout.split() == ["False", "2"], (run.stdout, run.stderr)
    assert len(run.stderr.strip().splitlines()) <= 2 and "error" in run.stderr  # one line (argparse: usage + line)
    assert not (tmp_path / "run").exists()


def test_the_client_refuses_frame_offsets_outside_the_chunk():
    from wamplan.wam.cosmos_client import CosmosClientConfig

    assert CosmosClientConfig(send_chunk_frames=(4, 8, 12)).send_chunk_frames == (4, 8, 12)
    for bad in ((0,), (16,), (4, 4)):
        with pytest.raises(ConfigError, match=r"--wam-send-chunk-frames must be distinct step offsets in 1\.\.15"):
            CosmosClientConfig(send_chunk_frames=bad)


def test_every_planner_has_its_config_in_the_settings_registry():
    """PLANNER_CONFIGS (torch-free, what the command line is built from) holds exactly the planners' configs."""
    assert {n: c.config_cls for n, c in PLANNERS.items()} == dict(PLANNER_CONFIGS)
