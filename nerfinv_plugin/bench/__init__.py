"""Experiment grids: many inversions (cases x variants x seeds) run, resumed and scored as the thesis
counts its results (chapter 5: successes over 30 runs, 3 trajectories 10 times each)."""
