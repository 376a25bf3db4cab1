"""The package's version: a leaf module that any layer may import (no imports of its own)."""

__version__ = "0.2.0"
