"""Experiments: the virtual-boundary campaign, the paper's simulation, the command sources, the results report."""
