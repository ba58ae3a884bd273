"""Pose math: frame conversions at the dataset boundary, SE(3) maps and pose errors."""
