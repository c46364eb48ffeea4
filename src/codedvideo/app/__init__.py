"""The application: the command line, `codedvideo run` and the report."""
