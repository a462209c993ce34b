"""``python -m sb3_cgac.compare``: see the package's docstring."""

from sb3_cgac.compare.cli import main

main()
