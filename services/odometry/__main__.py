import sys

from services.odometry.service import main

sys.exit(main())
