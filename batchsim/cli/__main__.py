"""`python -m batchsim.cli`: the `batchsim` command."""

import sys

from batchsim.cli import main

sys.exit(main())
