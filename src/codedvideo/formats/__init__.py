"""File formats: images, videos, npy, CACTI .mat, Zarr stores, outputs that never clobber."""
