"""The inversion engine: pixel samplers, losses, the batched candidate optimizer and the Monte Carlo
schedule along a trajectory."""
