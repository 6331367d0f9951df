"""taskvar_torch: offline learning across task variations for online performance, in PyTorch."""

__version__ = "0.1.0"
