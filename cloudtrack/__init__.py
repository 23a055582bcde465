"""Infrastructure shared by every CloudTrack process: configuration files, logging, the model store."""

__version__ = "0.1.0"
