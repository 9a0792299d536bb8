"""Per-step cost of every bundled scene: moreau_sim.bench.step_costs (python scripts/bench_step.py --help)."""

from moreau_sim.bench.step_costs import main

if __name__ == "__main__":
    main()
