"""Watching an inversion in a browser: a viser scene with nerfstudio's viewer conventions (the model's
training cameras, the observed frame, the candidates coloured by loss, the kept ones, the estimated and
true trajectories, the model's render at the best candidate beside the observed image), live during
``ns-invert --viewer`` or replayed from a run folder's candidate trail by ``ns-invert-view``."""
