"""Benchmarks behind ``ns-invert-bench``: experiment grids of many inversions (cases x variants x seeds) run,
resumed and scored as the thesis counts its results (chapter 5: successes over 30 runs, 3 trajectories 10
times each), and measurements of one model (speed against the thesis' implementation, screw origins, view
bank recall), each a function returning a typed result."""
