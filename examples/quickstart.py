"""Quick start: a code, a simulated capture, its video, its score — arrays in [0, 1], no files.

    python examples/quickstart.py
"""
import codedvideo as cv

video = cv.synthetic_scene("default", frames=8, size=(96, 96)) / 255  # truth: 8 sub-frames in [0, 1]
mask = cv.make_code("hitomi", video.shape[1:], frames=8, bump=2, seed=0)  # one bump of 2 sub-frames a pixel
coded = cv.simulate(video, mask, noise_sigma=0.005, seed=1)  # the one photograph the camera records
result = cv.reconstruct(coded, mask, noise_sigma=0.005, full_output=True)  # the shipped N = 8 dictionary
score = cv.evaluate(result.frames, video)
print(f"{result.frames.shape[0]} frames of {result.frames.shape[1]}x{result.frames.shape[2]}, data range "
      f"{result.data_range.value:g} ({result.data_range.source}): PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.3f}")
