"""Figure of one branched simulation: moreau_sim.bench.corner_branches (python scripts/corner_branches.py --help)."""

from moreau_sim.bench.corner_branches import main

if __name__ == "__main__":
    main()
