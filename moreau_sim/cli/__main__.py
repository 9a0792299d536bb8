"""`python -m moreau_sim.cli`: the `moreau-sim` command line."""

from . import main

main()
