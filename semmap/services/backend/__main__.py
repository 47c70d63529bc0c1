import sys

from semmap.services.backend.service import main

sys.exit(main())
