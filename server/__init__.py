"""burrforce server: cutting-force model, voxel bone, haptics, hot loop and control plane."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("burrforce")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
