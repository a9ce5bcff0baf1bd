"""The `phim` command line (phim/cli.py) and what its entry point sets up for every command."""
