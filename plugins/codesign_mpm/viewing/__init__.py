"""Seeing runs: `codesign render` (render.py: headless video and stills) and `codesign view`
(view.py: interactive 3-D recordings for Rerun)."""
