import sys

from services.backend.service import main

sys.exit(main())
