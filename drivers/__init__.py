"""Frame sources: everything that delivers images to the pipeline (replay, simulator, live cameras).

This is the bottom layer: it imports nothing else of calibcoach, and it owns the project's error
family (`calibcoach.drivers.errors`), so every stage above can raise it.
"""
