"""``python -m sofast_station`` runs the ``sofast-station`` command."""

import sys

from .cli import main

sys.exit(main())
