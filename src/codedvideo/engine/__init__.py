"""The engine: validated settings, tiling into Dask graphs over Zarr stores, the cache, the stages of a run."""
