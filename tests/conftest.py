import pytest


@pytest.fixture(scope="session")
def env():
    """One CubeInsertion-v1 instance for the whole session (creating one costs seconds)."""
    from wamplan.envs.core import InsertionEnv

    e = InsertionEnv()
    yield e
    e.close()
