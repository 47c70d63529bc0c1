import sys

from services.player.service import main

sys.exit(main())
