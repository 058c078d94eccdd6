"""The lab's tests (`make test-lab`, not part of `make test`) use the product tests' fixtures: tests/conftest.py is
loaded by path and its fixtures and hooks re-exported here (`repo_script` loads a script by its path from the
repository's root, e.g. ``repo_script("lab/tools/compare_runs.py")``)."""

import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location("_wamplan_product_conftest", Path(__file__).parents[1] / "tests" / "conftest.py")
_product = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_product)
globals().update({k: v for k, v in vars(_product).items() if not k.startswith("__")})
