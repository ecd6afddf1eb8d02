"""`python -m leveler.cli`: the `leveler` command."""

import sys

from leveler.cli.main import main

sys.exit(main())
