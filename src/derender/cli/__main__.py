"""``python -m derender.cli``: the ``derender`` command."""

from derender.cli import main

main()
