"""The ``lidarcal`` command line."""
