import importlib.util
import os
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).parents[1]


@pytest.fixture(scope="session")
def repo_script():
    """Load a script of the repository (``scripts/...``, ``benchmarks/...``; a path from the repository's root) as a
    module, so a test can call its functions."""
    def load(path: str) -> ModuleType:
        spec = importlib.util.spec_from_file_location(Path(path).stem, REPO / path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


# the files whose tests take longest, first: two workers that take files in this order (make test's `--dist
# loadfile`) finish together instead of one running a long file alone at the end
LONGEST_FIRST = ("test_ray.py", "test_proxy.py", "test_fidelity.py", "test_data.py", "test_readme.py",
                 "test_oracle.py", "test_errors.py", "test_wm_benchmark.py", "test_branch.py", "test_worldmodel.py")


def pytest_collection_modifyitems(config, items):
    """The longest files first (:data:`LONGEST_FIRST`, the rest in their order). Tests marked `gpu` need an
    accelerator: without one they are reported as skipped, not silently absent."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's tests keep their order
    import torch

    if torch.accelerator.is_available():
        return
    skip = pytest.mark.skip(reason="needs a GPU (torch.accelerator finds none); run on a machine with one")
    for item in items:
        if item.get_closest_marker("gpu") is not None:
            item.add_marker(skip)


@pytest.fixture(scope="module")
def one_thread():
    """Tiny tensors run faster on one torch thread (and a busy 2-core box thrashes with two); a module opts in with
    ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(autouse=True, scope="session")
def _help_cache_in_tmp(tmp_path_factory):
    """`wamplan CMD --help` caches its text (wamplan.cli.main): the tests keep that cache out of the user's home."""
    mp = pytest.MonkeyPatch()
    mp.setenv("WAMPLAN_CACHE_DIR", str(tmp_path_factory.mktemp("wamplan_cache")))
    yield
    mp.undo()


@pytest.fixture(scope="session")
def env():
    """One CubeInsertion-v1 instance for the whole session (creating one costs seconds)."""
    from wamplan.envs.core import TaskEnv

    e = TaskEnv()
    yield e
    e.close()


@pytest.fixture(scope="session")
def small_env():
    """The same task rendered at 64 px, for tests where the resolution does not matter (renders cost less)."""
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv

    e = TaskEnv(EnvConfig(camera_size=64))
    yield e
    e.close()


@pytest.fixture(scope="session")
def expert_store(tmp_path_factory) -> Path:
    """Expert seeds 0 and 1 at 64 px, collected once for the whole session (about 20 s).

    Shared: treat it as read-only. A test that writes into a store (collects more episodes, caches features,
    trains a world model on it) works on a copy: ``shutil.copytree(expert_store, tmp_path / "expert")``.
    """
    from filelock import FileLock

    from wamplan.cli import main

    # under pytest-xdist each worker's base temp lies in one directory of this run: the first worker to ask
    # collects the store there and the others wait for it, then read it
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = tmp_path_factory.getbasetemp().parent / "session_store"
        shared.mkdir(exist_ok=True)
    else:
        shared = tmp_path_factory.mktemp("session_store")
    root, done = shared / "expert", shared / "expert.done"
    with FileLock(str(shared / "expert.lock")):
        if not done.is_file():
            assert main(["collect", "--source", "expert", "--episodes", "2", "--out", str(root), "--camera-size",
                         "64"]) == 0
            done.touch()
    return root


@pytest.fixture
def refused(capsys):
    """``refused(argv, *parts)``: run ``wamplan ARGV`` expecting a refusal (exit status 2) whose last line on stderr
    holds every one of ``parts``; returns that line."""
    from wamplan.cli import main

    def check(argv, *parts) -> str:
        assert main([str(a) for a in argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        for part in parts:
            assert part in err, err
        return err

    return check
