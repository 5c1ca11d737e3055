"""``python -m backend.cli`` is ``mosaic-afm``."""

import sys

from backend.cli import main

sys.exit(main())
