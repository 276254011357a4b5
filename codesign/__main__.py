"""Allows ``python -m codesign``, which works where no console script is on PATH."""

from codesign.cli import main

main()
