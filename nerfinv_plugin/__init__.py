"""nerfinv: 6D pose estimation by inverting trained nerfstudio models."""

__version__ = "0.1.0"
