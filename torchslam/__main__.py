"""``python -m torchslam`` runs the ``torchslam`` command."""

import sys

from torchslam.cli import main

sys.exit(main())
