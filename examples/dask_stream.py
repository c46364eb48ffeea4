"""A coded camera's stream as a dask array, reconstructed lazily on a local dask.distributed cluster.

    python examples/dask_stream.py [SCHEDULER_ADDRESS]

Each capture is one chunk; the same graph runs on any cluster (dask-jobqueue for Slurm or PBS): give its
scheduler's address.
"""
import sys

import dask.array as da
import distributed
import numpy as np

import codedvideo as cv

captures, n, size = 4, 8, (64, 64)
video = cv.synthetic_scene("default", frames=captures * n, size=size) / 255
masks = np.stack([cv.make_code("hitomi", size, frames=n, bump=2, seed=s) for s in range(captures)])
coded = da.from_array(cv.simulate(video, masks), chunks=(1, *size))  # (T, H, W), one chunk a capture

if __name__ == "__main__":
    if len(sys.argv) > 1:
        client = distributed.Client(sys.argv[1])
    else:
        client = distributed.Client(distributed.LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1",
                                                             dashboard_address=None))
    with client:
        frames = cv.reconstruct(coded, masks, data_range=1.0)  # lazy: nothing computed yet
        result = frames.compute()
        workers = len(client.nthreads())
    score = cv.evaluate(result, video)
    print(f"{captures} captures -> {result.shape[0]} frames on {workers} workers: "
          f"PSNR {score['psnr']:.2f} dB")
