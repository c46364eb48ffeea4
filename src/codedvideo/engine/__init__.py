"""The engine: validated settings, tiling into Dask graphs over Zarr stores, the cache, the methods, and the stages of a run (training, simulation, reconstruction, the pipeline)."""
