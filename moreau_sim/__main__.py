"""`python -m moreau_sim`: the `moreau-sim` command line."""

from .cli import main

main()
