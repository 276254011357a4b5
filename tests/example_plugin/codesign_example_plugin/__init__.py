"""Example third-party codesign plugin."""
