"""``python -m floxels_ext ...``: the ``floxels`` command."""

import sys

from floxels_ext.cli import main

sys.exit(main())
