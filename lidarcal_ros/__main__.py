"""``python -m lidarcal_ros`` runs the ``lidarcal`` command line."""

import sys

from lidarcal_ros.cli.main import main

if __name__ == "__main__":  # (not when a spawned child process imports the main module)
    sys.exit(main())
