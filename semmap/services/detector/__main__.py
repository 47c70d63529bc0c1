import sys

from semmap.services.detector.service import main

sys.exit(main())
