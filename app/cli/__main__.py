"""``python3 -m app.cli`` is ``tirdeflect``."""

import sys

from app.cli.main import main

sys.exit(main())
