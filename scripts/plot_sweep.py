"""Figure from a restitution sweep of the bouncing ball: moreau_sim.bench.plot_sweep."""

from moreau_sim.bench.plot_sweep import main

if __name__ == "__main__":
    main()
