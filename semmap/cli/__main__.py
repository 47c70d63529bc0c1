"""`python -m semmap.cli`: the `semmap` command without the installed entry point."""

import sys

from semmap.cli.main import main

sys.exit(main())
