"""Spreading one run's episodes over workers (Ray) without losing or repeating any."""
