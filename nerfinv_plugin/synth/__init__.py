"""Synthetic scenes, trajectories and datasets rendered with Mitsuba 3 (CPU ``scalar_rgb`` variant)."""
