"""Data: synthetic scenes, held-out footage, the manifest, the shipped dictionaries."""
