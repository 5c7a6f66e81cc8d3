"""``python -m lidarcal_ros`` runs the ``lidarcal`` command line."""

from lidarcal_ros.cli.main import console_main

if __name__ == "__main__":  # (not when a spawned child process imports the main module)
    console_main()
