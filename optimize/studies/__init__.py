"""Studies over rollouts: the paper comparison, sweeps, sensitivities, every controller at its own optimum."""
