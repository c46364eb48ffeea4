"""codedvideo: video from a single coded-exposure photograph (Hitomi et al., ICCV 2011)."""

__version__ = "0.1.0"
