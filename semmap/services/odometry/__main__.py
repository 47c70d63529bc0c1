import sys

from semmap.services.odometry.service import main

sys.exit(main())
