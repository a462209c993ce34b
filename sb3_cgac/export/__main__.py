"""``python -m sb3_cgac.export``: see the package's docstring."""

from sb3_cgac.export.cli import main

main()
