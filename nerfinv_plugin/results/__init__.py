"""What a run leaves behind: the typed records of its files (a frame's result, a Monte Carlo step, the
summary), the run folder that writes and reads them, the summary's numbers, and the one atomic writer.
``inversion`` writes them and ``report`` and ``bench`` read them; this package imports neither."""
