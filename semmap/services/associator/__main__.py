import sys

from semmap.services.associator.service import main

sys.exit(main())
