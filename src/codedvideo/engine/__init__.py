"""The engine: validated settings, the methods, tiling into Dask graphs over Zarr stores, the cache, and the stages
of a run (training, simulation, reconstruction, the pipeline)."""
