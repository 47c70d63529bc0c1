import sys

from semmap.services.player.service import main

sys.exit(main())
