"""The package version (one place: setup reads it from here, torch_hsh and the CLI import it)."""
__version__ = "0.2.0.dev0"
