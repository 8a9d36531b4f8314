"""The package version (``pyproject.toml`` holds the same number), apart so that modules can read it without
importing the package ``__init__`` that imports them."""

__version__ = "0.1.0"
