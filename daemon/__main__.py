"""``python -m retargetd.daemon`` runs the ``retargetd`` console script."""

import sys

from retargetd.daemon.cli.main import main

sys.exit(main())
