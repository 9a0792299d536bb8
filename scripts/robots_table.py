"""The table of bundled robot scenes in docs/robots.md: moreau_sim.bench.robots_table."""

from moreau_sim.bench.robots_table import main

if __name__ == "__main__":
    raise SystemExit(main())
