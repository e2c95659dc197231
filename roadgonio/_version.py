"""The version of roadgonio, in the base layer so that every room can read it without importing
the package's API (``roadgonio/__init__.py`` re-exports it)."""
__version__ = "0.1.0"
