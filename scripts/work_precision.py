"""Work-precision benchmark: moreau_sim.bench.work_precision (see --help)."""

from moreau_sim.bench.work_precision import main

if __name__ == "__main__":
    raise SystemExit(main())
