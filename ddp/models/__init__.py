"""The Dream Diffusion Policy model and its training-time helpers."""
