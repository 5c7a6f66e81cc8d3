"""``python -m lidarcal_ros`` runs the ``lidarcal`` command line."""

import sys

from lidarcal_ros.cli.main import main

sys.exit(main())
