"""stereodem: the application (CLI, configuration, end-to-end pipeline)."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("stereodem")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0+unknown"
