"""The stress suite side by side: moreau_sim.bench.stability (python scripts/stability.py --help)."""

from moreau_sim.bench.stability import main

if __name__ == "__main__":
    raise SystemExit(main())
