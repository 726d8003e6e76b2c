"""Figures, drawn with matplotlib's object API (no pyplot state) and written atomically."""
