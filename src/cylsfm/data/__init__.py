"""Datasets, loaders and synthetic scenes."""
