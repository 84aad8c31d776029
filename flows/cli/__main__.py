"""`python -m flows.cli` is `sim2act`."""

import sys

from flows.cli import main

sys.exit(main())
