"""facesynth: facial-detail synthesis from markers and low-resolution animation."""

__version__ = "0.1.0"
