"""Friction laws at the contact point: one abstract Module (`base.py`), one file per law."""
