"""``python -m wamplan.cli``: the same as the ``wamplan`` command."""

import sys

from wamplan.cli.main import main

sys.exit(main())
