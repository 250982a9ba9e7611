"""``python -m floxels_ext ...`` runs the ``floxels`` command line."""

import sys

from .cli import main

sys.exit(main())
