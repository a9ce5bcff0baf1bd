"""`python -m phim ...`: the same as the `phim` command."""

from phim.cli import main

main(prog_name="phim")
