"""codedvideo: video from a single coded-exposure photograph (Hitomi et al., ICCV 2011).

The public API (:mod:`codedvideo.api`) is loaded on first use, so ``import codedvideo`` stays light::

    import codedvideo as cv
    mask = cv.make_code("hitomi", (256, 256), frames=8, bump=2)
    frames = cv.reconstruct(cv.simulate(video, mask), mask)
"""

__version__ = "0.1.0"

#: The public API: these names load :mod:`codedvideo.api` (and numpy) on first use.
__all__ = ["CodedVideoError", "ConfigError", "InputError", "Reconstruction", "ReconstructSettings", "SensorModel",
           "evaluate", "load_dictionary", "make_code", "reconstruct", "simulate", "synthetic_scene", "train"]


def __getattr__(name: str):
    if name in __all__:
        from codedvideo import api

        return getattr(api, name)
    raise AttributeError(f"module 'codedvideo' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
