import sys

from semmap.services.tracker.service import main

sys.exit(main())
