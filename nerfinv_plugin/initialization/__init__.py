"""Starting poses from the model alone: the object in the observed frame, a view bank of the model, matching."""
