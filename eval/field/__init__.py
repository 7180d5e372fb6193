"""Field runs over a bed: the loop whichever bot films, the simulated bed scored against its
truth, and the physical bot's bed, which has none."""
