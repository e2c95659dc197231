"""Example studies of ``roadgonio intercompare`` (installed as ``roadgonio.studies``; usable by name)."""
