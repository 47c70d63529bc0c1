import sys

from services.associator.service import main

sys.exit(main())
