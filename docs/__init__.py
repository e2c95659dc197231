"""The documentation shipped with roadgonio: ``conventions.md``, the physics conventions."""
