import sys

from semmap.services.viz.service import main

sys.exit(main())
