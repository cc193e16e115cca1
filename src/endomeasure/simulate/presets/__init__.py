"""Built-in simulator presets (JSON data files, read with importlib.resources)."""
