"""``python -m ocpkit.cli``: the `ocpkit` command."""

import sys

from ocpkit.cli import main

sys.exit(main())
