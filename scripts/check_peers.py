"""Every available peer against the exact references: moreau_sim.bench.check_peers."""

from moreau_sim.bench.check_peers import main

if __name__ == "__main__":
    raise SystemExit(main())
