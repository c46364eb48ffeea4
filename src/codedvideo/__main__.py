"""``python -m codedvideo ...``: the command line."""
from codedvideo.app.cli import console_main

console_main()
