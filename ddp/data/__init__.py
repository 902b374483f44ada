"""Demonstration data: sources, storage, normalisation and sequence sampling."""
