import sys

from services.tracker.service import main

sys.exit(main())
