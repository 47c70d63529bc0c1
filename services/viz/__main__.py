import sys

from services.viz.service import main

sys.exit(main())
