"""Reading observed sequences (SHIRT, Blender splits, image folders) and SPEED+ for training."""
